"""A local colony of daemon processes on loopback (demo, benchmark, tests): start, watch, stop."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import zenoh

from colonyd.runtime import open_session, zenoh_config
from colonyd.status import alive_members, query_status

_GIVEN: set[int] = set()
#: where daemons' ports come from: below the kernel's ephemeral range, so no outgoing
#: connection and no `bind(port 0)` (Zenoh's own sockets, other test workers) can take a port
#: between our pick and the daemon's bind
PORT_FLOOR = 20000


def _ephemeral_floor() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _bindable(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port() -> int:
    """A currently free TCP port on 127.0.0.1, never the same twice in one process, taken from
    below the ephemeral range (each process starts at its own offset) when there is room."""
    hi = _ephemeral_floor()
    span = hi - PORT_FLOOR
    if span >= 1000:
        first = (os.getpid() * 7919) % span
        for i in range(span):
            port = PORT_FLOOR + (first + len(_GIVEN) + i) % span
            if port not in _GIVEN and _bindable(port):
                _GIVEN.add(port)
                return port
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port not in _GIVEN:
            _GIVEN.add(port)
            return port


@dataclass
class LocalDaemon:
    """One `colonyd run` subprocess."""

    agent: str
    port: int
    state_dir: Path
    log_path: Path
    args: list[str]
    proc: subprocess.Popen[bytes] | None = None
    env: dict[str, str] = field(default_factory=dict)
    host: str = "127.0.0.1"  # its address (another one inside a network namespace)
    prefix: list[str] = field(default_factory=list)  # e.g. ["ip", "netns", "exec", NS]
    transport: str = "tcp"  # or "tls" (with a zenoh_config naming the certificates)

    @property
    def endpoint(self) -> str:
        return f"{self.transport}/{self.host}:{self.port}"

    def start(self) -> None:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        log = open(self.log_path, "ab")  # noqa: SIM115 - owned by the child
        try:
            self.proc = subprocess.Popen(
                [*self.prefix, sys.executable, "-m", "colonyd", "run", *self.args],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                env={**os.environ, **self.env},
                # A session of its own, as systemd starts a service: where the kernel shares CPU
                # time by session (autogroup), the colony is not one share of the machine.
                start_new_session=True,
            )
        finally:
            log.close()

    def listening(self) -> bool:
        """True once the process listens on its port (read from /proc/<pid>/net/tcp, its own
        network namespace's table: no connection made)."""
        if self.proc is None:
            return False
        want = f":{self.port:04X}"
        try:
            table = Path(f"/proc/{self.proc.pid}/net/tcp").read_text()
        except OSError:  # the process is gone
            return False
        for line in table.splitlines()[1:]:
            fields = line.split()
            if fields[1].endswith(want) and fields[3] == "0A":  # local address, state LISTEN
                return True
        return False

    def wait_listening(self, timeout: float = 30.0) -> None:
        """Return once the daemon listens on its port; TimeoutError if it dies or never does."""
        deadline = time.monotonic() + timeout
        while not self.listening():
            if not self.alive() or time.monotonic() > deadline:
                msg = f"{self.agent} is not listening on {self.endpoint} after {timeout:.0f} s"
                raise TimeoutError(msg)
            time.sleep(0.05)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            assert self.proc is not None
            os.kill(self.proc.pid, sig)

    def stop(self, timeout: float = 8.0) -> int | None:
        """SIGTERM, then SIGKILL after `timeout`; returns the exit code."""
        self.terminate()
        return self.reap(time.monotonic() + timeout)

    def terminate(self) -> None:
        """Ask the daemon to stop (SIGCONT first, in case it is frozen, then SIGTERM)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGCONT)
            self.proc.terminate()

    def reap(self, deadline: float) -> int | None:
        """Wait for the exit until `deadline` (monotonic), then SIGKILL; the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            try:
                self.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


def stop_all(daemons: list[LocalDaemon], timeout: float = 8.0) -> None:
    """Stop daemons all at once (SIGTERM to each, then wait; SIGKILL after `timeout`): each
    one's shutdown (final snapshot, export, session close) overlaps the others'."""
    for d in daemons:
        d.terminate()
    deadline = time.monotonic() + timeout
    for d in daemons:
        d.reap(deadline)


class LocalColony:
    """Daemons on 127.0.0.1 with multicast off and a fresh namespace; the first is the hub."""

    def __init__(
        self,
        base: Path,
        *,
        colony: str = "local",
        namespace: str | None = None,
        lease_ms: int | None = None,
        heartbeat_s: float = 0.5,
        extra: list[str] | None = None,
        multicast: bool = False,
        transport: str = "tcp",
        zenoh_config: Path | None = None,
    ) -> None:
        self.base = Path(base)
        self.base.mkdir(parents=True, exist_ok=True)
        self.colony = colony
        self.namespace = namespace or f"{colony}-{uuid.uuid4().hex[:10]}"
        self.lease_ms = lease_ms
        self.heartbeat_s = heartbeat_s
        self.extra = list(extra or [])
        self.multicast = multicast  # only ever inside a private network namespace (tests)
        self.transport = transport
        self.zenoh_config = zenoh_config  # extra Zenoh JSON5 (TLS) for daemons and observer
        self.daemons: dict[str, LocalDaemon] = {}
        self._session: zenoh.Session | None = None
        self._session_endpoints: list[str] = []

    def add(
        self,
        agent: str,
        sources: list[str] | None = None,
        *,
        start: bool = True,
        extra: list[str] | None = None,
        host: str = "127.0.0.1",
        prefix: list[str] | None = None,
    ) -> LocalDaemon:
        port = free_port()
        hub = next((d for d in self.daemons.values() if d.alive()), None)
        hub = hub or next(iter(self.daemons.values()), None)
        args = [
            "--colony",
            self.colony,
            "--namespace",
            self.namespace,
            "--agent-id",
            agent,
            "--state-dir",
            str(self.base / agent),
            "--listen",
            f"{self.transport}/{host}:{port}",
            "--heartbeat-s",
            str(self.heartbeat_s),
        ]
        if not self.multicast:
            args.append("--no-multicast")
        if hub is not None and not self.multicast:
            args += ["--connect", hub.endpoint]
            if start and hub.alive():
                hub.wait_listening()  # connect to a listening hub, not to a process still starting
        if self.lease_ms:
            args += ["--lease-ms", str(self.lease_ms)]
        for spec in sources or []:
            args += ["--source", spec]
        args += self.extra + list(extra or [])
        d = LocalDaemon(
            agent,
            port,
            self.base / agent,
            self.base / f"{agent}.log",
            args,
            host=host,
            prefix=list(prefix or []),
            transport=self.transport,
        )
        if self.zenoh_config is not None:
            d.env["COLONYD_ZENOH_CONFIG"] = str(self.zenoh_config)
        self.daemons[agent] = d
        if start:
            d.start()
        return d

    # -- observation ----------------------------------------------------------------------
    def session(self) -> zenoh.Session:
        """The observer's session, connected to every daemon listening so far (reopened as
        daemons come up, so the observer never depends on gossip to reach one: a session opened
        while a daemon was still starting, as on a cold start, never reached it)."""
        endpoints = [d.endpoint for d in self.daemons.values() if d.alive() and d.listening()]
        if self._session is not None and endpoints != self._session_endpoints:
            self._session.close()
            self._session = None
        if self._session is None:
            conf = zenoh_config(
                mode="peer",
                listen=[f"{self.transport}/127.0.0.1:0"],
                connect=endpoints,
                multicast=False,
                gossip=True,
                extra_file=self.zenoh_config,
            )
            self._session = open_session(conf)
            self._session_endpoints = endpoints
            time.sleep(0.2)  # let the links come up before the first query
        return self._session

    def status(
        self, *, digest: bool = False, samples: bool = False, timeout: float = 2.0
    ) -> list[dict[str, Any]]:
        return query_status(
            self.session(), self.namespace, digest=digest, samples=samples, timeout=timeout
        )

    def members(self) -> list[str]:
        return alive_members(self.session(), self.namespace)

    def converged(
        self, agents: list[str] | None = None, status_timeout: float = 2.0
    ) -> tuple[bool, str]:
        """True when every listed daemon holds every listed origin's layer, identical to it
        (`status_timeout`: for the digests, a pass over every layer a daemon holds). The digests
        are asked for only once a round without them finds every origin done and its seq held
        everywhere: each costs every daemon a pass over every layer it holds, and a watcher
        calling this twice a second while the colony maps or catches up (the demo) had the
        daemons spend more CPU on digests than on scan matching."""
        agents = agents or [a for a, d in self.daemons.items() if d.alive()]
        cheap = {r["agent"]: r for r in self.status(timeout=status_timeout)}
        ok, reason = _layers_agree(cheap, agents, digest=False)
        if not ok:
            return ok, reason
        reports = {r["agent"]: r for r in self.status(digest=True, timeout=status_timeout)}
        return _layers_agree(reports, agents, digest=True)

    def _still_mapping(self, agents: list[str] | None) -> tuple[bool, str]:
        """(True, why) while a listed daemon is missing, still mapping or has unpublished
        changes."""
        agents = agents or [a for a, d in self.daemons.items() if d.alive()]
        reports = {r["agent"]: r for r in self.status()}
        for agent in agents:
            r = reports.get(agent)
            if r is None:
                return True, f"no status from {agent}"
            if not r.get("sources_done") or r.get("unpublished"):
                return True, f"{agent} is still mapping"
        return False, ""

    def wait_converged(
        self, timeout: float, agents: list[str] | None = None, status_timeout: float = 2.0
    ) -> float:
        """Seconds until converged; raises TimeoutError with the last reason. `status_timeout`:
        of each round of status with digests (longer for layers of millions of voxels)."""
        t0 = time.monotonic()
        reason = "not checked"
        while time.monotonic() - t0 < timeout:
            # Digests cost each daemon a pass over every layer it holds: ask for them only once
            # mapping is over, so watching a colony does not slow down what it watches.
            mapping, reason = self._still_mapping(agents)
            if mapping:
                time.sleep(0.3)
                continue
            ok, reason = self.converged(agents, status_timeout)
            if ok:
                return time.monotonic() - t0
            time.sleep(0.3)
        raise TimeoutError(f"colony did not converge in {timeout:.0f} s: {reason}")

    def reports(
        self, agents: Iterable[str], *, within: float = 20.0, timeout: float = 2.0, **query: Any
    ) -> dict[str, dict[str, Any]]:
        """One round of status reports, by agent, in which every one of `agents` answered (asked
        again until one does, for up to `within` s; TimeoutError naming the missing ones). A
        daemon that misses a round's `timeout` on a loaded machine is otherwise simply absent;
        `query` goes to `status`."""
        want = list(agents)
        deadline = time.monotonic() + within
        while True:
            got = {r["agent"]: r for r in self.status(timeout=timeout, **query)}
            missing = [a for a in want if a not in got]
            if not missing:
                return got
            if time.monotonic() > deadline:
                msg = f"no status report from {missing} in one round within {within:.0f} s"
                raise TimeoutError(msg)
            time.sleep(0.2)

    def wait_status(
        self,
        until: Callable[[list[dict[str, Any]]], bool],
        within: float = 30.0,
        agents: Iterable[str] = (),
        **query: Any,
    ) -> list[dict[str, Any]]:
        """Status reports once every agent in `agents` answered and `until(reports)` holds, or the
        last ones after `within` seconds (the caller's assertions then say what is missing);
        `query` goes to `status`. Naming the agents keeps a slow reply from making a condition
        over "every report" hold for the ones that came."""
        want = set(agents)
        deadline = time.monotonic() + within
        while True:
            reports = self.status(**query)
            answered = want <= {r["agent"] for r in reports}
            if (answered and until(reports)) or time.monotonic() > deadline:
                return reports
            time.sleep(0.2)

    def wait_members(self, n: int, timeout: float = 30.0) -> None:
        """Return once `n` daemons answered one status round (a round ends when every daemon
        answered; its 3 s bound lets a busy one count, which 1 s did not on a loaded machine)."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            if len(self.status(timeout=3.0)) >= n:
                return
            time.sleep(0.2)
        raise TimeoutError(f"fewer than {n} daemons answered within {timeout:.0f} s")

    def logs(self, tail: int = 3000) -> str:
        """The end of every daemon's log, for error reports."""
        out = []
        for d in self.daemons.values():
            if d.log_path.exists():
                out.append(f"--- {d.agent}\n" + d.log_path.read_text(errors="replace")[-tail:])
        return "\n".join(out)

    def close(self) -> None:
        """Stop every daemon (SIGTERM, then SIGKILL) and close the observer session."""
        try:
            if self._session is not None:
                self._session.close()
                self._session = None
        finally:
            stop_all(list(self.daemons.values()))

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _layers_agree(
    reports: dict[str, dict[str, Any]], agents: list[str], *, digest: bool
) -> tuple[bool, str]:
    """(True, "converged") when every one of `agents` answered in `reports`, is done mapping
    with nothing unpublished, and holds every listed origin's layer at its origin's seq (and,
    with `digest`, its origin's digest); else (False, why)."""
    missing = [a for a in agents if a not in reports]
    if missing:
        return False, f"no status from {missing}"
    for origin in agents:
        own = reports[origin]
        if not own.get("sources_done") or own.get("unpublished"):
            return False, f"{origin} is still mapping"
        want = own["layers"].get(origin)
        if want is None or want["seq"] == 0:
            continue
        for a in agents:
            have = reports[a]["layers"].get(origin)
            if (
                have is None
                or have["seq"] != want["seq"]
                or (digest and have["digest"] != want["digest"])
            ):
                return False, f"{a} lacks {origin}@{want['seq']} (has {have and have['seq']})"
    return True, "converged"
