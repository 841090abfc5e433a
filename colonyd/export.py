"""Export: a daemon serves its fused or per-layer map; `colonyd export` writes them as files."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np
import zenoh

from colonyd.config import Config
from colonyd.errors import NoAnswerError, StatusError
from colonyd.layers import SURFACE_REACH
from colonyd.mapping import write_floor_plan
from colonyd.outdir import output_dir
from colonyd.runtime import get_client_session
from protocol.keyexpr import EXPORT, NAME_PATTERN, status_key, status_selector
from voxel import keys as vk
from voxel.octomap_io import write_bt
from voxel.ply import write_ply

#: Sub-folder of `colonyd export --out` for the layers not aligned with the colony frame.
UNALIGNED = "unaligned"
#: Most voxels an export reply may carry (a reply is bounded like any network input).
MAX_EXPORT_VOXELS = 50_000_000


@dataclass
class MapReply:
    """One map as a daemon sent it: voxel keys and log-odds in `frame`."""

    agent: str
    layer: str | None
    frame: str
    resolution: float
    keys: np.ndarray  # (N, 3) int64
    logodds: np.ndarray  # (N,) float32
    layers: list[str] = field(default_factory=list)
    classes: np.ndarray | None = None  # (N,) int16 most probable class, -1 none (if sent)
    #: (M, 3) points of the occupied voxels (log-odds >= 0, in order): their surface points
    #: (`layers.fused_surface`); None: their centres.
    points: np.ndarray | None = None

    def occupied_points(self) -> np.ndarray:
        """Points (M, 3) of the occupied voxels: `points`, else their centres."""
        if self.points is not None:
            return self.points
        return vk.keys_to_centers(self.keys[self.logodds >= 0], self.resolution)


def export_time(text: str | None) -> float | None:
    """The time of an export query's `at` parameter (seconds), None when absent; ValueError
    unless a finite number (a query from the network: the daemon answers a bad one with
    nothing)."""
    if text is None:
        return None
    t = float(text)
    if not math.isfinite(t):
        msg = f"expected a finite time, found {text!r}"
        raise ValueError(msg)
    return t


def parse_time(text: str, flag: str) -> float:
    """Seconds (Unix) of a command-line time: a number of seconds, an ISO 8601 date-time (UTC
    unless it says otherwise), or `-N` for N seconds before now; StatusError otherwise."""
    import datetime as dt

    try:
        t = float(text)
        return time.time() + t if t < 0 else t
    except ValueError:
        pass
    try:
        stamp = dt.datetime.fromisoformat(text)
    except ValueError:
        msg = f"{flag}: expected seconds, -SECONDS (before now) or an ISO 8601 time, found {text!r}"
        raise StatusError(msg) from None
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=dt.UTC)
    return stamp.timestamp()


def encode_map(reply: MapReply) -> bytes:
    """The bytes a daemon answers an export query with (classes and points when it has them:
    the points as float32 offsets from the occupied voxels' centres)."""
    body = {
        "agent": reply.agent,
        "layer": reply.layer,
        "frame": reply.frame,
        "resolution": float(reply.resolution),
        "n": len(reply.keys),
        "keys": np.ascontiguousarray(reply.keys, "<i4").tobytes(),
        "logodds": np.ascontiguousarray(reply.logodds, "<f4").tobytes(),
        "layers": reply.layers,
    }
    if reply.classes is not None:
        body["classes"] = np.ascontiguousarray(reply.classes, "<i2").tobytes()
    if reply.points is not None:
        centres = vk.keys_to_centers(reply.keys[reply.logodds >= 0], reply.resolution)
        body["surface"] = np.ascontiguousarray(reply.points - centres, "<f4").tobytes()
    answer: bytes = msgpack.packb(body, use_bin_type=True)
    return answer


def decode_map(data: bytes) -> MapReply:
    """A map reply, checked field by field (it came from the network); StatusError if bad."""
    try:
        d = msgpack.unpackb(data, raw=False, max_bin_len=MAX_EXPORT_VOXELS * 12)
        n = int(d["n"])
        if (
            not 0 <= n <= MAX_EXPORT_VOXELS
            or len(d["keys"]) != 12 * n
            or len(d["logodds"]) != 4 * n
        ):
            msg = f"expected {n} voxels of 12 key and 4 log-odds bytes, found other sizes"
            raise ValueError(msg)
        resolution = float(d["resolution"])
        if not 0 < resolution <= 10:
            raise ValueError(f"expected a resolution in (0, 10] m, found {resolution}")
        layers = [str(x) for x in d.get("layers", [])]
        classes = None
        if d.get("classes") is not None:
            if len(d["classes"]) != 2 * n:
                msg = f"expected {n} classes of 2 bytes, found {len(d['classes'])} bytes"
                raise ValueError(msg)
            classes = np.frombuffer(d["classes"], "<i2").astype(np.int16)
        keys = np.frombuffer(d["keys"], "<i4").reshape(n, 3).astype(np.int64)
        logodds = np.frombuffer(d["logodds"], "<f4").astype(np.float32)
        points = None
        if d.get("surface") is not None:
            occupied = logodds >= 0
            m = int(np.count_nonzero(occupied))
            if len(d["surface"]) != 12 * m:
                msg = f"expected {m} surface offsets of 12 bytes, found {len(d['surface'])} bytes"
                raise ValueError(msg)
            offsets = np.frombuffer(d["surface"], "<f4").reshape(m, 3)
            if not np.isfinite(offsets).all():
                raise ValueError("expected finite surface offsets, found NaN or infinity")
            worst, bound = float(np.abs(offsets).max(initial=0.0)), SURFACE_REACH * resolution
            if worst > bound * (1 + 1e-3):
                msg = f"expected surface offsets within {bound:g} m per axis, found {worst:g} m"
                raise ValueError(msg)
            points = vk.keys_to_centers(keys[occupied], resolution) + offsets
        return MapReply(
            str(d["agent"]),
            None if d["layer"] is None else str(d["layer"]),
            str(d["frame"]),
            resolution,
            keys,
            logodds,
            layers,
            classes,
            points,
        )
    except (ValueError, KeyError, TypeError, msgpack.exceptions.ExtraData) as exc:
        msg = (
            f"export reply: expected a map (agent, frame, resolution, keys, log-odds), found: {exc}"
        )
        raise StatusError(msg) from None


#: RGB per object class (class id modulo its length): strong colours, none on the height ramp's
#: blue-green-yellow.
CLASS_COLOURS = np.array(
    [
        (230, 60, 50),
        (250, 150, 30),
        (200, 60, 200),
        (140, 90, 40),
        (255, 110, 180),
        (120, 120, 120),
        (170, 0, 60),
        (255, 215, 160),
    ],
    np.uint8,
)


def map_colours(points: np.ndarray, classes: np.ndarray | None) -> np.ndarray:
    """RGB (N, 3) uint8 of voxels at `points`: its class's colour where it has one, else its
    height on a blue (low) to yellow (high) ramp between the 2nd and 98th percentile of the
    heights."""
    n = len(points)
    if n == 0:
        return np.zeros((0, 3), np.uint8)
    z = points[:, 2]
    lo, hi = np.percentile(z, [2, 98])
    level = np.clip((z - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    import cv2  # loads where a map is exported, not at start-up

    ramp = cv2.applyColorMap(level.reshape(-1, 1), cv2.COLORMAP_VIRIDIS).reshape(n, 3)
    colours: np.ndarray = ramp[:, ::-1].copy()  # BGR -> RGB
    if classes is not None:
        labelled = classes >= 0
        colours[labelled] = CLASS_COLOURS[classes[labelled].astype(np.int64) % len(CLASS_COLOURS)]
    return colours


def write_maps(reply: MapReply, out: Path, stem: str) -> dict[str, Path]:
    """`<stem>.bt` (occupied and free), `<stem>.ply` (the occupied voxels' points: surface
    points where the map has them, else centres; coloured by class and by height where
    unlabelled), and a floor plan when every occupied voxel lies in one z layer (a 2D map)."""
    out.mkdir(parents=True, exist_ok=True)
    occupied = reply.logodds >= 0
    files = {f"{stem}.bt": out / f"{stem}.bt", f"{stem}.ply": out / f"{stem}.ply"}
    write_bt(files[f"{stem}.bt"], reply.resolution, reply.keys, occupied)
    points = reply.occupied_points()
    classes = None if reply.classes is None else reply.classes[occupied]
    write_ply(files[f"{stem}.ply"], points, map_colours(points, classes))
    z = reply.keys[occupied, 2]
    if stem == "fused" and z.size and z.min() == z.max():
        files.update(
            write_floor_plan(
                out, reply.keys[occupied], reply.keys[~occupied], int(z[0]), reply.resolution
            )
        )
    return files


def query_maps(
    session: zenoh.Session, namespace: str, params: str, timeout: float, agent: str | None = None
) -> list[MapReply]:
    """Map replies of every daemon (or of daemon `agent` only) to an export query with `params`
    ("k=v;k=v")."""
    where = (
        status_selector(namespace, EXPORT)
        if agent is None
        else status_key(namespace, agent, EXPORT)
    )
    replies = session.get(
        where + (f"?{params}" if params else ""),
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout,
    )
    return [decode_map(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]


def fetch_maps(
    session: zenoh.Session,
    namespace: str,
    *,
    layer: str | None = None,
    agent: str | None = None,
    wait_s: float = 5.0,
    at: float | None = None,
    layers_too: bool = True,
) -> tuple[MapReply, dict[str, MapReply]]:
    """The fused map of the daemon `agent` (or the first to answer, by agent id) and its layers'
    maps (every layer of the colony frame, or only `layer`; none without `layers_too`); with
    `at`, as they were at that time."""
    when = "" if at is None else f"at={float(at)!r}"
    deadline = time.monotonic() + wait_s
    answered: set[str] = set()
    while True:
        replies = query_maps(session, namespace, when, 5.0)
        answered.update(r.agent for r in replies)
        fused = [r for r in replies if agent is None or r.agent == agent]
        if fused or time.monotonic() >= deadline:
            break
        time.sleep(0.3)
    if not fused:
        others = f": expected one of those that did: {', '.join(sorted(answered))}"
        msg = (
            f"daemon {agent!r} of colony namespace {namespace!r} did not answer an export query "
            f"within {wait_s:g} s{others if answered else ''}"
            if agent
            else f"no daemon of colony namespace {namespace!r} answered an export query within "
            f"{wait_s:g} s"
        )
        raise NoAnswerError(msg)
    source = min(fused, key=lambda r: r.agent)
    layers: dict[str, MapReply] = {}
    names = [layer] if layer is not None else source.layers if layers_too else []
    for name in names:
        got = fetch_layer(session, namespace, source.agent, name, at)
        if got is None:
            msg = (
                f"daemon {source.agent!r} holds no layer {name!r}: expected an agent id whose "
                f"layer it holds (its fused map's: {', '.join(source.layers) or 'none'}; "
                "`colonyd status` lists every member's layers)"
            )
            raise StatusError(msg)
        layers[name] = got
    return source, layers


def fetch_layer(
    session: zenoh.Session, namespace: str, agent: str, name: str, at: float | None = None
) -> MapReply | None:
    """The map of layer `name` as daemon `agent` holds it (with `at`, as it was then); None if
    it does not hold it. Asked of `agent` alone: every daemon holding a replica of the layer
    sent its copy, all but one thrown away."""
    when = "" if at is None else f"at={float(at)!r}"
    params = ";".join(p for p in (f"layer={name}", when) if p)
    got = [r for r in query_maps(session, namespace, params, 10.0, agent) if r.agent == agent]
    return got[0] if got else None


def _check_names(layer: str | None, agent: str | None) -> None:
    import re

    for name, value in (("layer", layer), ("agent", agent)):
        if value is not None and not re.fullmatch(NAME_PATTERN, value):
            msg = f"--{name}: expected a name matching {NAME_PATTERN}, found {value!r}"
            raise StatusError(msg)


@dataclass
class Changes:
    """What appeared (occupied now, not at `since`) and disappeared (occupied at `since`, not
    now) in one map, as voxel keys."""

    since: float
    frame: str
    resolution: float
    appeared: np.ndarray  # (A, 3)
    disappeared: np.ndarray  # (D, 3)


def diff_maps(before: MapReply, after: MapReply, since: float) -> Changes:
    """Occupied voxels of `after` not occupied in `before`, and the other way round."""
    occ_before = vk.pack(before.keys[before.logodds >= 0])
    occ_after = vk.pack(after.keys[after.logodds >= 0])
    appeared = vk.unpack(np.setdiff1d(occ_after, occ_before))
    disappeared = vk.unpack(np.setdiff1d(occ_before, occ_after))
    return Changes(since, after.frame, after.resolution, appeared, disappeared)


def changes_between(fetch: Callable[[float], MapReply], since: float, until: float) -> Changes:
    """What changed between the maps `fetch` gives as they were at `since` and at `until`, both
    from the layers' history. A history keeps each voxel's log-odds as of its last state change
    (VOXEL.md, "History"), not its present value: a fused voxel summed from such values can be
    occupied where the live sum is free, so comparing the map at `since` with the live map
    reported voxels of an unchanged colony as appeared or disappeared."""
    return diff_maps(fetch(since), fetch(until), since)


def map_changes(
    config: Config,
    out: Path,
    since: float,
    *,
    layer: str | None = None,
    agent: str | None = None,
    wait_s: float = 5.0,
) -> tuple[Changes, dict[str, Path]]:
    """What changed in the fused map (or one `layer`) of a running colony since a time:
    `appeared.ply` and `disappeared.ply` (occupied voxel centres) in `out`, and the counts."""
    _check_names(layer, agent)
    output_dir(out, "--out")
    session = get_client_session(config, "changes")

    def fetch(at: float) -> MapReply:
        nonlocal agent
        fused, layers = fetch_maps(
            session,
            config.key_namespace,
            layer=layer,
            agent=agent,
            wait_s=wait_s,
            at=at,
            layers_too=layer is not None,
        )
        agent = fused.agent  # both from the same daemon
        return fused if layer is None else layers[layer]

    try:
        changes = changes_between(fetch, since, max(time.time(), since))
    except NoAnswerError as exc:
        raise NoAnswerError(_why(exc, session, config, agent, wait_s)) from None
    finally:
        session.close()
    out.mkdir(parents=True, exist_ok=True)
    files = {"appeared.ply": out / "appeared.ply", "disappeared.ply": out / "disappeared.ply"}
    for name, keys in (
        ("appeared.ply", changes.appeared),
        ("disappeared.ply", changes.disappeared),
    ):
        write_ply(files[name], vk.keys_to_centers(keys, changes.resolution))
    return changes, files


def _why(
    exc: NoAnswerError, session: zenoh.Session, config: Config, agent: str | None, wait_s: float
) -> str:
    """A named daemon that did not answer keeps its message; nobody at all gets the reason
    `colonyd status` gives (the colonies this session does see, or none)."""
    from colonyd.status import nobody_answered

    return str(exc) if agent else nobody_answered(session, config, wait_s)


def export_maps(
    config: Config,
    out: Path,
    *,
    layer: str | None = None,
    agent: str | None = None,
    wait_s: float = 5.0,
    at: float | None = None,
) -> tuple[str, dict[str, Path]]:
    """Fetch the fused map in the colony frame and every layer's map (or one `layer`) from a
    running colony (the daemon `agent`, or the first to answer), as they are or were `at` a
    time, and write them into `out`; returns the fused map's frame and the files. The layers
    that daemon holds but has not aligned with the colony frame are not in the fused map: each
    is written in its own frame under `out/unaligned/` (`UNALIGNED`), not left out unsaid."""
    _check_names(layer, agent)
    output_dir(out, "--out")
    session = get_client_session(config, "export")
    try:
        fused, layers = fetch_maps(
            session, config.key_namespace, layer=layer, agent=agent, wait_s=wait_s, at=at
        )
        apart: dict[str, MapReply] = {}
        if layer is None:
            for name in unaligned_layers(session, config.key_namespace, fused):
                got = fetch_layer(session, config.key_namespace, fused.agent, name, at)
                if got is not None:  # else dropped meanwhile: nothing to write
                    apart[name] = got
    except NoAnswerError as exc:
        raise NoAnswerError(_why(exc, session, config, agent, wait_s)) from None
    finally:
        session.close()
    files: dict[str, Path] = {}
    if layer is None:
        files.update(write_maps(fused, out, "fused"))
    for name, reply in layers.items():
        files.update(write_maps(reply, out, name))
    for name, reply in apart.items():
        (out / UNALIGNED).mkdir(exist_ok=True)
        written = write_maps(reply, out / UNALIGNED, name)
        files.update({f"{UNALIGNED}/{key}": path for key, path in written.items()})
    return fused.frame, files


def unaligned_layers(session: zenoh.Session, namespace: str, fused: MapReply) -> list[str]:
    """The layers with data that the daemon which sent `fused` holds but has not fused (not
    aligned with its colony frame), from its status report."""
    from colonyd.status import query_status

    report = next((r for r in query_status(session, namespace) if r["agent"] == fused.agent), {})
    held = report.get("layers", {})
    return sorted(o for o, v in held.items() if v.get("seq") and o not in fused.layers)
