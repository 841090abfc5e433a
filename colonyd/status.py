"""Status: each daemon answers status queries; `colonyd status` gathers and prints them."""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from colonyd.activity import Activity
from colonyd.config import Config
from colonyd.errors import StatusError
from colonyd.runtime import get_client_session, undeclare
from colonyd.worker import Bounded, Worker
from protocol import KeyExprError
from protocol.keyexpr import (
    ALIVE,
    ROOT,
    alive_subscription,
    parse_key,
    status_key,
    status_selector,
)


@dataclass
class _Asked:
    """A query as the Zenoh callback took it."""

    query: zenoh.Query
    at: float  # time.monotonic() then


def asked_timeout_ms(text: str) -> int:
    """A query's `timeout_ms` parameter: 1 to 10 decimal digits, at most 2^32 - 1; anything
    else (a peer's bytes) is ignored as if absent (0: no deadline)."""
    if not re.fullmatch(r"[0-9]{1,10}", text):
        return 0
    return min(int(text), 0xFFFF_FFFF)


class StatusServer:
    """Answers `colony/<ns>/<agent>/<report>` queries (status: `answer(params)` as JSON; export:
    the map bytes `answer(params)` returns; None: no reply), one at a time on a worker. A query
    whose `timeout_ms` parameter passed while it waited in the queue is dropped unanswered: its
    requester has gone (a watcher asking for digests of a large layer every few hundred ms would
    otherwise queue passes over the layer nobody waits for)."""

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        agent: str,
        answer: Callable[[dict[str, str]], Any],
        report: str = "status",
        activity: Activity | None = None,
    ) -> None:
        self._answer_params = answer
        self._worker: Worker[_Asked] = Worker(
            report,
            self._answer,
            Bounded(16),
            describe=lambda a: f"a {report} query on {a.query.key_expr}",
            done=lambda a: a.query.drop(),
            activity=activity,
        )
        self._queryable = session.declare_queryable(
            status_key(namespace, agent, report),
            lambda q: self._worker.put(_Asked(q, time.monotonic())),
        )
        self._worker.start()

    def _answer(self, asked: _Asked) -> None:
        query = asked.query
        # zenoh's stub types Parameters.__iter__ as returning a list, not an iterator
        params = {str(k): str(v) for k, v in query.parameters}  # type: ignore[attr-defined]
        waits = asked_timeout_ms(params.pop("timeout_ms", ""))
        if waits and time.monotonic() - asked.at > waits / 1000:
            return  # its requester has gone
        body = self._answer_params(params)
        if body is None:  # nothing to say (an export of a layer not held)
            return
        if not isinstance(body, bytes):
            body = json.dumps(body).encode()
        query.reply(str(query.key_expr), body)

    def close(self) -> None:
        self._worker.close()
        undeclare(self._queryable)


def query_status(
    session: zenoh.Session,
    namespace: str,
    *,
    digest: bool = False,
    samples: bool = False,
    timeout: float = 3.0,
) -> list[dict[str, Any]]:
    """One status report per daemon reachable in the namespace, sorted by agent id."""
    params = [f"timeout_ms={int(timeout * 1000)}"]  # the server drops it once we have gone
    if digest:
        params.append("digest=1")
    if samples:
        params.append("samples=1")
    selector = status_selector(namespace) + "?" + ";".join(params)
    out = [r for r in json_replies(session, selector, timeout) if "agent" in r]
    return sorted(out, key=lambda r: r["agent"])


def json_replies(session: zenoh.Session, selector: str, timeout: float) -> list[dict[str, Any]]:
    """The JSON objects every daemon answering `selector` replied (error replies and anything
    else skipped)."""
    out = []
    for reply in session.get(selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout):
        if reply.ok is None:
            continue
        try:
            answer = json.loads(reply.ok.payload.to_bytes())
        except ValueError:
            continue
        if isinstance(answer, dict):
            out.append(answer)
    return out


def alive_members(session: zenoh.Session, namespace: str, timeout: float = 2.0) -> list[str]:
    """Agents whose liveliness token is visible."""
    agents = set()
    for r in session.liveliness().get(alive_subscription(namespace), timeout=timeout):
        if r.ok is not None:
            try:
                agents.add(parse_key(str(r.ok.key_expr)).origin)
            except KeyExprError:
                continue
    return sorted(agents)


def colonies_seen(session: zenoh.Session, timeout: float = 1.0) -> set[str]:
    """Colony namespaces of the live daemons this session reaches (their liveliness tokens)."""
    seen: set[str] = set()
    for r in session.liveliness().get(f"{ROOT}/*/{ALIVE}/*", timeout=timeout):
        if r.ok is not None:
            try:
                seen.add(parse_key(str(r.ok.key_expr)).colony)
            except KeyExprError:
                continue
    return seen


def nobody_answered(session: zenoh.Session, config: Config, wait_s: float) -> str:
    """Why no daemon answered: the colonies whose daemons this session does see (a wrong
    `--colony`), or none at all (nothing listens where it looked)."""
    where = (
        ", ".join(config.connect)
        if config.connect
        else "multicast scouting"
        if config.multicast
        else "nowhere (no --connect, multicast off)"
    )
    seen = colonies_seen(session)
    head = (
        f"no daemon of colony namespace {config.key_namespace!r} answered within {wait_s:g} s "
        f"(looked through {where})"
    )
    if seen:
        names = ", ".join(repr(n) for n in sorted(seen))
        return (
            f"{head}: expected a member of that colony, found daemons of {names} only: "
            "give --colony (or --namespace)"
        )
    return f"{head}: expected a running colonyd there, found none"


def collect_status(
    config: Config, *, digest: bool = False, samples: bool = False, wait_s: float = 3.0
) -> list[dict[str, Any]]:
    """Open a short-lived session, wait until every live member answers, return their reports."""
    session = get_client_session(config, "status")
    try:
        deadline = time.monotonic() + wait_s
        reports: list[dict[str, Any]] = []
        while True:
            expected = set(alive_members(session, config.key_namespace, timeout=1.0))
            reports = query_status(
                session,
                config.key_namespace,
                digest=digest,
                samples=samples,
                timeout=max(0.5, min(3.0, deadline - time.monotonic())),
            )
            for r in reports:
                expected |= {m["agent"] for m in r.get("members", []) if m.get("alive")}
            if expected and {r["agent"] for r in reports} >= expected:
                return reports
            if time.monotonic() >= deadline:
                break
            time.sleep(0.2)
        if not reports:
            raise StatusError(nobody_answered(session, config, wait_s))
        return reports
    finally:
        session.close()


def behind(reports: list[dict[str, Any]]) -> dict[str, int]:
    """For each agent, how many deltas it lacks summed over origins, versus the best holder."""
    best: dict[str, tuple[int, int]] = {}
    for r in reports:
        for origin, layer in r.get("layers", {}).items():
            v = (int(layer["epoch"]), int(layer["seq"]))
            best[origin] = max(best.get(origin, (0, 0)), v)
    out = {}
    for r in reports:
        lag = 0
        layers = r.get("layers", {})
        for origin, (epoch, seq) in best.items():
            mine = layers.get(origin)
            if mine is None or int(mine["epoch"]) != epoch:
                lag += seq
            else:
                lag += max(0, seq - int(mine["seq"]))
        out[r["agent"]] = lag
    return out


def format_status(reports: list[dict[str, Any]]) -> str:
    """Human table: one member per line, then its layers."""
    lags = behind(reports)
    now = time.time()
    seen: dict[str, float] = {}
    for r in reports:  # last seen: latest of the member's own report and what its peers heard
        seen[r["agent"]] = max(seen.get(r["agent"], 0.0), float(r.get("time", now)))
        for m in r.get("members", []):
            seen[m["agent"]] = max(seen.get(m["agent"], 0.0), float(m.get("last_seen", 0.0)))
    lines = [
        f"{'agent':<16} {'kind':<8} {'last seen':>9} {'pose':<22} {'behind':>6} "
        f"{'objects':>7}  layers"
    ]
    for r in reports:
        pose = ",".join(f"{x:.2f}" for x in r.get("pose", [])[:3]) or "-"
        ago = f"{max(0.0, now - seen.get(r['agent'], now)):.1f}s"
        layers = " ".join(
            f"{o}@{v['seq']}({v['voxels']})" for o, v in sorted(r.get("layers", {}).items())
        )
        objects = len(r.get("objects", []))
        heard = ",".join(f"{o}:{len(v)}" for o, v in sorted(r.get("peer_objects", {}).items()))
        lines.append(
            f"{r['agent']:<16} {r.get('kind', '?'):<8} {ago:>9} {pose:<22} "
            f"{lags.get(r['agent'], 0):>6} {objects:>7}  {layers}"
            + (f"  objects heard: {heard}" if heard else "")
        )
    answered = {r["agent"] for r in reports}
    for agent in sorted(set(seen) - answered):  # known to peers but not answering (frozen, gone)
        kind = next(
            (
                m.get("kind", "?")
                for r in reports
                for m in r.get("members", [])
                if m["agent"] == agent
            ),
            "?",
        )
        ago = f"{max(0.0, now - seen[agent]):.1f}s"
        alive = [
            m.get("alive", True)
            for r in reports
            for m in r.get("members", [])
            if m["agent"] == agent
        ]
        # its liveliness token withdrawn (a clean stop, or a lease that ran out) for every
        # member that knows it: it left; else it is there but does not answer (frozen, busy)
        state = "(left)" if alive and not any(alive) else "(not answering)"
        lines.append(f"{agent:<16} {kind:<8} {ago:>9} {'-':<22} {'?':>6} {'?':>7}  {state}")
    lines.extend(frame_lines(reports, sorted(seen)))
    lines.extend(source_lines(reports))
    return "\n".join(lines)


def source_lines(reports: list[dict[str, Any]]) -> list[str]:
    """Each answering member's sources: frames in its layer (those from before a restart, when
    a recording resumed), frames skipped, and whether a recording was read to its end."""
    lines = []
    for r in reports:
        for s in r.get("sources", []):
            frames = s.get("position", s.get("delivered", 0))
            text = f"{r['agent']}: source {s.get('spec', '?')}: {frames} frames"
            if s.get("resumed_after"):
                text += f" ({s['resumed_after']} from before a restart)"
            if s.get("skipped"):
                text += f", {s['skipped']} skipped"
            if s.get("done"):
                text += ", read to its end"
            lines.append(text)
    return lines


def frame_lines(reports: list[dict[str, Any]], members: list[str]) -> list[str]:
    """The colony frame as the answering members see it: its root, the members aligned with it
    and those that are not (one line per distinct view, naming who holds it; `--json` has each
    member's transforms and alignment attempts)."""
    views: dict[tuple[str, tuple[str, ...]], list[str]] = {}
    for r in reports:
        frame = r.get("colony_frame") or {}
        key = (str(frame.get("root", "?")), tuple(sorted(frame.get("agents", {}))))
        views.setdefault(key, []).append(r["agent"])
    lines = []
    for (root, aligned), holders in sorted(views.items()):
        apart = [m for m in members if m not in aligned]
        seen_by = "" if len(views) == 1 else f" (as {', '.join(sorted(holders))} see it)"
        lines.append(
            f"colony frame: root {root}; aligned: {', '.join(aligned) or 'none'}; "
            f"not aligned: {', '.join(apart) or 'none'}{seen_by}"
        )
    return lines
