"""The daemon: recover, open the session, map, gossip, report, and shut down cleanly."""

from __future__ import annotations

import faulthandler
import importlib
import itertools
import logging
import math
import os
import signal
import sys
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from colonyd import heap
from colonyd.aligner import Aligner
from colonyd.alignment import ColonyFrame, Edge, align_layers, edge_of
from colonyd.colonymap import ColonyMaps
from colonyd.config import Config, load_config
from colonyd.errors import ColonydError, DuplicateAgentError, PersistenceError, StoppedError
from colonyd.estimator import (
    Estimator,
    PoseError,
    ScanEstimator,
    get_estimator,
    scan_estimator,
)
from colonyd.export import MapReply, encode_map, export_time, write_maps
from colonyd.fixes import fix_covariance, fix_in_own_frame, sightings_covariance, through
from colonyd.frames import Sender, colony_key, frame_of, get_receiver
from colonyd.gossip import Gossip
from colonyd.identity import get_trust, identity_path, load_signer
from colonyd.landmarks import colony_landmarks
from colonyd.layers import (
    FusedMap,
    Layers,
    best_class,
    fused,
    fused_surface,
    layer_weights,
    relabel,
)
from colonyd.logs import setup_logging
from colonyd.mapping import integrate_observation
from colonyd.membership import Membership, agent_alive
from colonyd.memory import limit_arenas
from colonyd.metrics import Metrics
from colonyd.notify import Notifier
from colonyd.objects import OwnObjects, to_wire
from colonyd.outdir import output_dir
from colonyd.persistence import StateStore
from colonyd.provenance import agent_bias, agent_reliability, pose_error
from colonyd.resume import EstimatorState, Positions, agrees
from colonyd.rosout import Ros2Outputs, RosPublishers
from colonyd.runtime import get_session
from colonyd.status import StatusServer, colonies_seen
from colonyd.threadclock import stamp
from colonyd.tombstones import OWN_LAYER, forget_params, load_tombstones, save_tombstones
from colonyd.worker import Throttle, held_text
from plugins.observation import AGENT_LABEL, ObjectDetection, Observation
from plugins.source import open_source
from plugins.stream import Source
from protocol import PoseFix
from voxel import kernels
from voxel.localisation import frame_error, se2
from voxel.localisation.sightings import frame_from_sightings

if TYPE_CHECKING:
    import zenoh

    from voxel.delta import Delta

log = logging.getLogger(__name__)

#: The own object list is published again every this many refreshes, changed or not.
OBJECTS_REPEAT = 5

#: The shortest time between two heartbeats when one is asked for early (a liveliness join, a
#: forget request): joins come from liveliness tokens, which nobody authenticates, and a stranger
#: declaring and undeclaring tokens made a daemon send one every 10 ms to the whole colony.
MIN_EARLY_HEARTBEAT_S = 0.25
#: Own alignments are offered again every this many alignment rounds, so that members that
#: joined later (or missed an offer) learn them and compute the same colony frame.
OFFERS_REPEAT = 3

#: An offered alignment is withdrawn after this many refusals in a row on grown maps (a pose
#: that more data keeps refuting was wrong: a wrong merge is worse than none).
WITHDRAW_AFTER = 3

#: Alignment round period (s) of a daemon that only re-offers a surveyed `site_pose`.
SITE_OFFER_S = 5.0

#: A heartbeat claiming our origin with another epoch is from a live duplicate when its time is
#: within this many seconds of ours (older ones are replays).
FRESH_S = 30.0
#: A CCTV sends no fix for a robot marker detected with less confidence than this.
MIN_FIX_CONFIDENCE = 0.15
#: Confidence of an alignment found from sightings (registration's are 0-1 by overlap and fit).
SIGHTING_CONFIDENCE = 0.5
#: Observers whose sightings of us are kept at once (each at most 50).
MAX_SIGHTED = 16
#: The compiled kernels load once the catch-ups that the first heartbeats start are done (they
#: share the interpreter lock): a wait of this many seconds for those heartbeats, then until
#: catch-up is idle, at most KERNELS_WAIT_S in all.
KERNELS_SETTLE_S = 0.5
KERNELS_WAIT_S = 10.0
#: Heartbeat periods after start at which a daemon with --connect endpoints and no member yet
#: says so (and which other colonies' daemons it reaches there).
LONELY_HEARTBEATS = 10
#: Modules the periodic jobs of a daemon with sources import on first use in its own process
#: (object clustering, localisation against own and colony maps),
#: imported with the kernels' loading instead, so that the daemon's start-up ends at a moment it
#: reports (`warm` in its status) and what they allocate is frozen out of the collector's passes
#: at once (`heap.Freezer`) rather than a few at a time as the jobs first run. A daemon without
#: sources imports none of them (~0.6 CPU-s). Registration's own modules (scipy.ndimage,
#: scipy.fft) load in the aligner's worker process, never here.
WARM_IMPORTS = (
    "sklearn.cluster",  # only where objects are clustered: `objects_s`, sources that label
    "scipy.spatial",  # cKDTree: scan matching (`ScanLocaliser`) and colony maps
)
#: The interpreter's thread switch interval in a daemon (Python's default is 5 ms).
SWITCH_INTERVAL_S = 0.001


def get_store(config: Config) -> StateStore:
    return StateStore(config.state_dir, config.agent_id, config.resolution, config.block_shape)


def get_sources(
    config: Config, stop: threading.Event, session: Callable[[], Any] | None = None
) -> list[Source]:
    """The configured sources; those whose spec sets no seed take one derived from the agent id;
    network sources (`ros2:`) read through `session()` once mapping starts."""
    seed = zlib.crc32(config.agent_id.encode()) % (1 << 16)
    return [
        open_source(spec, resolution=config.resolution, seed=seed + i, stop=stop, session=session)
        for i, spec in enumerate(config.sources)
    ]


def may_label(source: Source) -> bool:
    """Whether `source`'s observations may carry class ids (objects to cluster): its adapter says
    so with `labels` (LiDARs and synthetic points do not); one that says nothing may."""
    return bool(getattr(source.adapter, "labels", True))


#: Seconds between estimates of the own bias against aligned peers (colonyd/provenance.py).
BIAS_S = 30.0


class Daemon:
    """One colony member. `run()` reads as the table of contents of its life."""

    def __init__(
        self, config: Config, config_path: Path | None = None, flags: dict[str, Any] | None = None
    ) -> None:
        self.config = config
        self._config_path = config_path
        self._flags = flags or {}
        self.stop = threading.Event()
        self.reload = threading.Event()
        self.notifier = Notifier()
        self.metrics = Metrics()
        self.pose: list[float] = [0.0, 0.0, 0.0]
        self.started = time.time()
        self._published_local = 0
        self._last_snapshot = time.monotonic()
        self._publishing = threading.Lock()  # one publish step at a time (`_publish_once`)
        self._sources_done = threading.Event()
        #: Start-up is over: kernels loaded, first-use imports done (`_warm_up`).
        self.warm = threading.Event()
        self.freezer = heap.Freezer()  # start-up's objects out of the collector's passes
        self.objects = OwnObjects(frozenset(config.structure_classes))
        # registration in a worker process, started on first use
        self.aligner = Aligner(None if config.align_session_nice < 0 else config.align_session_nice)
        self._estimators: dict[str, Estimator] = {}  # per source spec
        self._own_edges: dict[str, Edge] = {}  # peer -> the alignment we last offered
        self.fused_map = FusedMap()  # the live fused view, kept layer by layer
        self._colony_maps: dict[str, ColonyMaps] = {}  # per source spec with a scan estimator
        self._estimate_s = 0.0  # running mean of one estimator step, seconds
        #: PoseFix messages for us (a CCTV saw our marker), applied by the mapping thread.
        self._fixes: deque[PoseFix] = deque(maxlen=32)
        self._forget_log = Throttle()  # refused forget requests: anyone may send them
        #: Fixes of observers not aligned with us: (pose seen, our estimate then) per observer.
        self._sightings: dict[str, deque[tuple[np.ndarray, np.ndarray]]] = {}
        self.pose_matrix: np.ndarray | None = None  # the latest sensor pose estimate (own frame)
        self.pose_covariance: np.ndarray | None = None
        self.truth_matrix: np.ndarray | None = None
        self.pose_error = PoseError()
        self.attempts: dict[str, dict[str, Any]] = {}  # peer -> last alignment attempt (JSON)
        self.stopping: list[tuple[str, float]] = []  # shutdown steps: (name, monotonic end)
        self.conflict = ""  # set when another live daemon has our agent id and we give way
        self._conflict_logged = 0.0
        #: The last state-directory error (disk full, read-only), "" once writing works again.
        self.state_error = ""
        self._state_error_logged = 0.0

    # -- table of contents ----------------------------------------------------------------
    def run(self) -> int:
        limit_arenas()  # before any thread allocates (colonyd/memory.py)
        self._install_signals()
        self.metrics.activity.watch_gc()
        cfg = self.config
        if cfg.export_dir is not None:  # found unwritable now, not at shutdown
            output_dir(cfg.export_dir, "export_dir")
        self.store = get_store(cfg)
        kernels.load_in_background()  # no scan or delta waits for a compilation (~36 CPU-s)
        try:
            # bad specs fail before the network is touched
            self._sources = get_sources(cfg, self.stop, lambda: self.session)
            self._recover()
            self.session = get_session(cfg)
            try:
                self._refuse_duplicate()
                self._declare()
                self._start_threads()
                self.notifier.ready(
                    f"colony {cfg.colony} agent {cfg.agent_id} seq {self.layers.own.seq}"
                )
                threading.Thread(target=self._warm_up, name="warm-up", daemon=True).start()
                log.info(
                    "ready: colony %s, agent %s, epoch %d, seq %d",
                    cfg.colony,
                    cfg.agent_id,
                    self.epoch,
                    self.layers.own.seq,
                )
                self._main_loop()
                self.stopping.append(("signal", time.monotonic()))
                self.notifier.stopping()
                log.info("stopping")
                self._shutdown()
            finally:
                self.session.close()
        finally:
            self.store.close()
        if self.stopping:
            _Laps(self.stopping)("session")
            took = self.stopping[-1][1] - self.stopping[0][1]
            steps = ", ".join(
                f"{name} {t1 - t0:.2f}" for (_, t0), (name, t1) in itertools.pairwise(self.stopping)
            )
            log.info("stopped in %.2f s (%s)", took, steps)
        else:
            log.info("stopped")
        if self.conflict:
            raise DuplicateAgentError(self.conflict)
        return 0

    # -- steps ----------------------------------------------------------------------------
    def _request_stop(self) -> None:
        """SIGTERM / SIGINT: stop, and wake the main loop now rather than at its next tick."""
        self.stop.set()
        gossip = getattr(self, "gossip", None)
        if gossip is not None:
            gossip.hb_now.set()

    def _install_signals(self) -> None:
        faulthandler.enable()  # a crash in native code still leaves Python stacks in the log
        faulthandler.register(signal.SIGUSR1, all_threads=True)  # stack dump for a stuck daemon
        signal.signal(signal.SIGTERM, lambda *_: self._request_stop())
        signal.signal(signal.SIGINT, lambda *_: self._request_stop())
        signal.signal(signal.SIGHUP, lambda *_: self.reload.set())

    def _recover(self) -> None:
        rec = self.store.recover()
        self.epoch = rec.epoch
        cfg = self.config
        signer = load_signer(identity_path(cfg.identity_file, cfg.state_dir))
        self.sender = Sender(
            cfg.agent_id,
            rec.epoch,
            key=colony_key(cfg.colony_key),
            signer=signer,
            first_seq=rec.frame_seq,
            reserve=self.store.reserve_frames,
        )
        self.layers = Layers(
            cfg.agent_id,
            cfg.resolution,
            ring_size=cfg.ring_size,
            max_layers=cfg.max_layers,
            max_peer_blocks=cfg.max_peer_blocks,
        )
        own = self.layers.own
        own.grid, own.epoch, own.seq = rec.grid, rec.epoch, rec.seq
        own.logged = int(rec.grid.version)  # all of it from the state directory, at rec.seq
        for seq, delta, created in rec.records[-cfg.ring_size :]:  # as published: for ranges
            own.remember(seq - 1, seq, relabel(delta, seq - 1, seq, time=created))
        own.grid.surface = cfg.surface  # whatever the snapshot was written with
        own.set_half_life(cfg.half_life_s)
        self.layers.forgotten = load_tombstones(cfg.state_dir)
        self.layers.on_forget = lambda _origin: save_tombstones(
            cfg.state_dir, self.layers.forgotten
        )
        self._last_forget = time.monotonic()
        self.bias = 0.0  # b: this agent's bias against aligned peers (colonyd/provenance.py)
        self._bias_at = time.monotonic()
        self._published_local = rec.published  # changes after it were never logged: send them
        #: Each recording's position, stored with the layer's versions (colonyd/resume.py).
        self.positions = Positions(rec.sources, list(cfg.sources))
        log.info(
            "state %s: %s, epoch %d, seq %d, %d log records replayed, layer digest %s",
            self.config.state_dir,
            "fresh" if rec.fresh else "recovered",
            rec.epoch,
            rec.seq,
            rec.wal_records,
            own.digest(),
        )

    def _duplicate(self, detail: str) -> str:
        cfg = self.config
        return (
            f"agent id {cfg.agent_id!r} is already in use in colony {cfg.colony!r} "
            f"(namespace {cfg.key_namespace!r}): {detail}; expected every daemon to have "
            "its own agent_id"
        )

    def _refuse_duplicate(self) -> None:
        """Refuse to start (before anything is declared or sent) if our agent id is taken."""
        if agent_alive(self.session, self.config.key_namespace, self.config.agent_id):
            raise DuplicateAgentError(self._duplicate("another colonyd holds its liveliness token"))

    def _on_own_origin(self, exc: Any) -> None:
        """A heartbeat with our origin: a replay, or a live duplicate that the start-up check
        missed (both started at once). Then the younger gives way; an established daemon keeps
        running and says so loudly."""
        now = time.time()
        if exc.epoch == self.epoch or abs(exc.time - now) > FRESH_S:
            log.warning("rejected a replayed heartbeat of our own origin: %s", exc)
            return
        self.metrics.add("duplicate_agent")
        text = self._duplicate(f"heard a heartbeat of epoch {exc.epoch} (ours is {self.epoch})")
        if now - self.started < max(5.0, 3 * self.config.heartbeat_s):
            self.conflict = text
            self.stop.set()
        elif now - self._conflict_logged > 10.0:
            self._conflict_logged = now
            log.error("%s; this daemon keeps running, the other should stop", text)

    def _declare(self) -> None:
        cfg = self.config
        ns = cfg.key_namespace
        self.gossip = Gossip(
            self.session,
            ns,
            self.layers,
            self.sender,
            get_receiver(
                cfg.colony_key,
                cfg.max_message_mb,
                cfg.agent_id,
                get_trust(cfg.trust, cfg.trusted_keys, cfg.state_dir),
            ),
            self.metrics,
            epoch=self.epoch,
            on_own_origin=self._on_own_origin,
            on_fix=self._fixes.append,
            inbox_size=cfg.inbox_size,
            inbox_bytes=int(cfg.inbox_mb * (1 << 20)),
            drop_rate=cfg.drop_rate,
            query_timeout_s=cfg.query_timeout_s,
            chunk_voxels=cfg.snapshot_chunk_voxels,
            history_sync_s=cfg.history_sync_s,
            peer_history_entries=cfg.peer_history_entries,
            history_push=cfg.history_push,
            max_members=cfg.max_members,
        )
        self.membership = member_table(self.session, cfg, self.gossip.on_member_event)
        self.status_server = StatusServer(
            self.session, ns, cfg.agent_id, self.report, activity=self.metrics.activity
        )
        self.export_server = StatusServer(
            self.session, ns, cfg.agent_id, self.export_map, report="export"
        )
        self.forget_server = StatusServer(
            self.session, ns, cfg.agent_id, self.forget_request, report="forget"
        )
        self.gossip.start(self.membership)
        self.ros: RosPublishers | None = None
        if cfg.ros2_publish:
            self.ros = RosPublishers(
                self.session,
                Ros2Outputs(
                    domain=cfg.ros2_domain,
                    node=cfg.ros2_node,
                    map_topic=cfg.ros2_map_topic,
                    cloud_topic=cfg.ros2_cloud_topic,
                    objects_topic=cfg.ros2_objects_topic,
                    frame=cfg.ros2_frame,
                    robot_frame=cfg.ros2_robot_frame,
                    grid_z_min=cfg.ros2_grid_z[0],
                    grid_z_max=cfg.ros2_grid_z[1],
                    max_points=cfg.ros2_max_points,
                    type_hashes=cfg.ros2_type_hashes,
                ),
            )

    def _warm_up(self) -> None:
        """Load the compiled kernels (optional; ~0.5 s of CPU) and import `WARM_IMPORTS` after
        the first catch-ups, which would otherwise share the interpreter with them, only when
        there are sources (nothing else integrates scans, localises or clusters); then `warm` is
        set. A scan integrated sooner starts the kernels' loading in a thread and takes the numpy
        path meanwhile (`kernels.load_in_background`)."""
        deadline = time.monotonic() + KERNELS_WAIT_S
        self.stop.wait(KERNELS_SETTLE_S)
        while not self.gossip.catchup.idle() and time.monotonic() < deadline:
            if self.stop.wait(0.05):
                return
        if self.stop.is_set():
            return
        if not self._sources:  # nothing integrates scans, localises or clusters here
            self.warm.set()
            return
        kernels.warm()
        kernels.warm_codec()
        clusters = self.config.objects_s > 0 and any(map(may_label, self._sources))
        for name in WARM_IMPORTS:
            if name.startswith("sklearn") and not clusters:
                continue  # ~90 MB of modules (RSS) a daemon that clusters nothing never needs
            try:
                importlib.import_module(name)
            except Exception as exc:  # noqa: BLE001 - the job that needs it says so when it runs
                # (an ImportError, or the import lock's deadlock error when a job's thread
                # imports a neighbouring module at the same moment): start-up still ends
                log.debug("warm-up: cannot import %s: %s", name, exc)
        self.warm.set()

    def _start_threads(self) -> None:
        self._threads = [
            threading.Thread(target=self._map_loop, name="mapping", daemon=True),
            threading.Thread(target=self._publish_loop, name="publisher", daemon=True),
        ]
        if self.config.objects_s > 0:
            self._threads.append(
                threading.Thread(target=self._objects_loop, name="objects", daemon=True)
            )
        site = self.config.site_matrix()
        if site is not None and self.config.anchor is not None:  # a surveyed pose: sure
            sure = Edge(
                self.config.agent_id,
                self.config.anchor,
                np.linalg.inv(site),
                1.0,
                0,
                0.0,
                np.zeros((6, 6)),
                time.time(),
            )
            self._offer(sure, "surveyed site_pose")
        if self.config.align_s > 0 or site is not None:
            self._threads.append(
                threading.Thread(target=self._align_loop, name="alignment", daemon=True)
            )
        if self.ros is not None:
            self._threads.append(threading.Thread(target=self._ros_loop, name="ros2", daemon=True))
        if self.config.connect:
            self._threads.append(
                threading.Thread(target=self._lonely_check, name="lonely-check", daemon=True)
            )
        if self.config.localise and self.config.colony_map_s > 0:
            self._threads.append(
                threading.Thread(target=self._colony_map_loop, name="colony-map", daemon=True)
            )
        for t in self._threads:
            t.start()

    def _main_loop(self) -> None:
        wd = self.notifier.watchdog_s
        next_hb = 0.0
        next_wd = 0.0
        last_hb = -math.inf
        while not self.stop.is_set():
            now = time.monotonic()
            with self.metrics.activity.timed("freeze"):
                self.freezer()  # what imports left, out of every later collector pass
            if self.reload.is_set():
                self.reload.clear()
                self._reload()
            early = self.gossip.hb_now.is_set() and now - last_hb >= MIN_EARLY_HEARTBEAT_S
            if now >= next_hb or early:
                self.gossip.hb_now.clear()
                last_hb = now
                try:
                    with self.metrics.activity.timed("heartbeat"):
                        self.gossip.heartbeat(self.config.kind, self.pose)
                    if self.pose_matrix is not None:
                        self.gossip.publisher.publish_pose(self.pose_matrix, self.pose_covariance)
                except PersistenceError as exc:  # no frame numbers could be reserved
                    self._state_failed(exc)
                next_hb = now + self.config.heartbeat_s
            if wd and now >= next_wd:
                mapping, publisher = self._threads[:2]
                if publisher.is_alive() and (mapping.is_alive() or self._sources_done.is_set()):
                    self.notifier.watchdog()
                next_wd = now + wd / 3
            timeout = next_hb - time.monotonic()
            if wd:
                timeout = min(timeout, next_wd - time.monotonic())
            if self.gossip.hb_now.is_set():  # asked for early, too soon after the last one
                soon = last_hb + MIN_EARLY_HEARTBEAT_S - time.monotonic()
                self.stop.wait(max(0.01, min(timeout, soon)))
            else:
                self.gossip.hb_now.wait(max(0.01, min(timeout, 0.5)))

    def _shutdown(self) -> None:
        lap = _Laps(self.stopping)
        self.stop.set()
        self.layers.own.nudge.set()  # the publisher's wait ends now
        self.aligner.close()  # an attempt under way ends now: the align thread can return
        for t in self._threads:
            t.join(timeout=3.0)
            if t.is_alive():
                log.warning("thread %s did not stop within 3 s; going on without it", t.name)
        lap("threads")
        own = self.layers.own
        try:
            self._publish_once(final=True)
            lap("final delta")
            if own.seq > 0:
                with own.lock:
                    self.store.snapshot(
                        own.grid, own.seq, self._published_local, self.positions.record()
                    )
            lap("snapshot")
        except PersistenceError as exc:  # the last good snapshot and the log stay as they were
            log.error("shutting down without a final snapshot: %s", exc)
        if self.config.export_dir is not None:
            self._export(self.config.export_dir)
            lap("export")
        if self.ros is not None:
            self.ros.close()
        self.status_server.close()
        self.export_server.close()
        self.forget_server.close()
        self.gossip.close()
        self.membership.close()
        lap("undeclare")

    def _export(self, directory: Path) -> None:
        try:
            reply = self.fused_reply()
            write_maps(reply, directory, self.config.agent_id)
            log.info(
                "fused map of %d layers (%d voxels) written to %s",
                len(reply.layers),
                len(reply.keys),
                directory,
            )
        except OSError as exc:
            log.error("cannot write the fused map to %s: %s", directory, exc)

    def _reload(self) -> None:
        """SIGHUP: re-read file + environment; apply rates, log level and key; report the rest."""
        self.notifier.reloading()
        try:
            new = load_config(self._config_path, **self._flags)
        except ColonydError as exc:
            log.error("reload failed, keeping the running configuration: %s", exc)
            self.notifier.ready()
            return
        live = {"publish_hz", "heartbeat_s", "snapshot_s", "log_level", "kind", "query_timeout_s"}
        changed = [k for k in type(new).model_fields if getattr(new, k) != getattr(self.config, k)]
        restart = [k for k in changed if k not in live]
        self.config = self.config.model_copy(
            update={k: getattr(new, k) for k in changed if k in live}
        )
        logging.getLogger().setLevel(self.config.log_level.upper())
        self.gossip.catchup.query_timeout_s = self.config.query_timeout_s
        log.info(
            "reloaded: %s%s",
            ", ".join(k for k in changed if k in live) or "nothing changed",
            f"; restart needed for {', '.join(restart)}" if restart else "",
        )
        self.notifier.ready()

    def _lonely_check(self) -> None:
        """Once, `LONELY_HEARTBEATS` heartbeat periods after start: a daemon given --connect
        endpoints that has met no member says so, naming the colonies whose daemons it does
        reach there (a --colony that differs from its peers' ran alone without a word)."""
        cfg = self.config
        if self.stop.wait(LONELY_HEARTBEATS * cfg.heartbeat_s):
            return
        if self.membership.table():  # peers only: a member joined (even if it left since)
            return
        others = sorted(colonies_seen(self.session) - {cfg.key_namespace})
        where = ", ".join(cfg.connect)
        if others:
            log.warning(
                "no member of colony namespace %r reached through %s, but daemons of %s: "
                "expected every member to run with the same --colony (or --namespace)",
                cfg.key_namespace,
                where,
                ", ".join(repr(o) for o in others),
            )
        else:
            log.info(
                "no member of colony namespace %r reached through %s yet (Zenoh keeps trying)",
                cfg.key_namespace,
                where,
            )

    # -- mapping (never waits on the network) ---------------------------------------------
    def _map_loop(self) -> None:
        """Recordings and simulations one after another; each live source (`ros2:`, which runs
        until the daemon stops) in a thread of its own, so that a robot's sensors all map."""
        live = [s for s in self._sources if getattr(s, "live", False)]
        threads = [
            threading.Thread(target=self._map_source, args=(s,), name=f"mapping-{i}", daemon=True)
            for i, s in enumerate(live)
        ]
        for t in threads:
            t.start()
        for source in self._sources:
            if self.stop.is_set():
                break
            if source not in live:
                self._map_source(source)
        for t in threads:
            t.join()
        self._sources_done.set()

    def _map_source(self, source: Source) -> None:
        own = self.layers.own
        began = time.monotonic()
        try:
            # a recording resumes where the recovered layer's evidence of it ends
            frames = self.positions.start(source, self.stop, lambda o: self._pass_over(source, o))
            if frames is None:
                return
            if source.spec not in self.positions.resumed:  # afresh: no passed-over frame counts
                self._estimators.pop(source.spec, None)
            stored = self.positions.restored(source.spec)
            if stored is not None:
                self._continue_estimate(source, stored)
            position = self.positions.resumed.get(source.spec, 0)
            for obs in frames:
                if self.stop.is_set():
                    break
                position += 1
                try:
                    with self.metrics.activity.timed("integrate"):
                        self._integrate(own, obs, source, position)
                except ValueError as exc:  # one bad frame (voxel/plugin input errors)
                    self.metrics.reject("bad-frame")
                    log.warning("source %s: frame skipped: %s", source.spec, exc)
                    with own.lock:  # not read again either
                        estimator = self._estimators.get(source.spec)
                        state = estimator.state() if isinstance(estimator, ScanEstimator) else None
                        self.positions.advance(source.spec, position, obs.frame, state)
                    continue
                self.metrics.add("frames")
        except (ColonydError, ValueError) as exc:  # the source itself failed
            log.error("source %s failed: %s", source.spec, exc)
            return
        except Exception:
            log.exception("source %s failed", source.spec)
            return
        if not self.stop.is_set():  # a recording's end: the daemon goes on serving its map
            self.positions.finished(source.spec)
            stats = source.stats
            reasons = ", ".join(f"{k} {v}" for k, v in sorted(stats.reasons.items()))
            passed = self.positions.resumed.get(source.spec, 0)
            log.info(
                "source %s done: %d frames in %.1f s%s, %d skipped%s",
                source.spec,
                stats.delivered,
                time.monotonic() - began,
                f" ({passed} of them passed over: already in the layer)" if passed else "",
                stats.skipped,
                f" ({reasons})" if reasons else "",
            )

    def _integrate(self, own: Any, obs: Observation, source: Source, position: int = 0) -> None:
        """Integrate one observation of `source`, its `position`-th (from 1, counting those
        the layer already held when it resumed)."""
        covariance = None
        state = None  # the estimator's state after this frame, stored with its evidence
        if self.config.localise and obs.odometry is not None:  # map from the estimate
            estimator = self._estimators.get(source.spec)
            if estimator is None:
                estimator = self._estimators[source.spec] = get_estimator(source.adapter, obs)
            started = time.perf_counter()
            obs = replace(obs, pose=estimator(obs))
            spent = time.perf_counter() - started
            self._estimate_s = (
                spent if not self._estimate_s else 0.95 * self._estimate_s + 0.05 * spent
            )
            if self._fixes and isinstance(estimator, ScanEstimator):
                self._apply_fixes(estimator)
            if obs.objects and isinstance(estimator, ScanEstimator):
                self._apply_landmarks(estimator, obs)
            self.pose_covariance = covariance = estimator.covariance()
            if isinstance(estimator, ScanEstimator) and self.positions.tracks(source.spec):
                state = estimator.state()
        seen = [d for d in obs.objects if d.label.startswith(AGENT_LABEL)]
        if seen:
            self._send_fixes(obs, seen)
        self.pose_error.update(obs.pose, obs.truth)  # evaluation only: never fed back
        with own.lock:
            integrate_observation(
                own.grid,
                obs,
                sensor=source.adapter.sensor_model,
                reliability=source.adapter.reliability,
                agent=self.config.agent_id,
                error=pose_error(covariance),
                agent_reliability=agent_reliability(
                    self.config.layer_weights, self.config.agent_id, self.config.kind
                ),
                bias=self.bias,
            )
            self.positions.advance(source.spec, position, obs.frame, state)
        self.objects.observe(obs)
        self.pose = [float(v) for v in obs.origin]
        self.pose_matrix = obs.pose
        self.truth_matrix = obs.truth  # evaluation only (a simulator's truth): reported, never used

    def _pass_over(self, source: Source, obs: Observation) -> None:
        """A frame a resumed recording passes over (its evidence is in the layer): only the
        estimator steps through it again, rebuilding its keyframe map and filter state."""
        if not (self.config.localise and obs.odometry is not None):
            return
        estimator = self._estimators.get(source.spec)
        if estimator is None:
            estimator = self._estimators[source.spec] = get_estimator(source.adapter, obs)
        try:
            estimator(obs)
        except ValueError as exc:  # as when the frame was integrated
            log.debug("source %s: passed-over frame refused by the estimator: %s", source.spec, exc)

    def _continue_estimate(self, source: Source, stored: EstimatorState) -> None:
        """After a resumed recording's passed-over frames: keep the estimator they rebuilt if
        it reached the stored pose (it read only the recording: the same estimate), else
        continue from the stored pose (what the layer was built with) with a new estimator,
        keyframes anew."""
        spec = source.spec
        estimator = self._estimators.get(spec)
        now = estimator.state() if isinstance(estimator, ScanEstimator) else None
        if now is not None and agrees(now, stored):
            log.info(
                "source %s: its estimator, stepped again through the passed-over frames, "
                "reached the stored pose: it continues with its keyframe map",
                spec,
            )
            return
        self._estimators.pop(spec, None)
        if self.config.localise:  # else no estimator is used
            restored = self._estimators[spec] = scan_estimator(source.adapter)
            restored.restore(stored)
        log.info(
            "source %s: its estimator continues from the stored pose (x %.3f, y %.3f, yaw "
            "%.4f)%s; its keyframe map starts anew from there",
            spec,
            *stored.pose,
            "" if now is None else f", not the {now.pose.round(3).tolist()} the frames gave again",
        )

    # -- pose fixes (a fixed camera tells a robot where it saw it) -------------------------
    def _send_fixes(self, obs: Observation, seen: list[ObjectDetection]) -> None:
        """Each robot marker seen (a CCTV): that robot's body pose in our frame, to that robot,
        with `fix_covariance`'s error; detections under `MIN_FIX_CONFIDENCE` (small, blurred
        markers) are not sent."""
        for det in seen:
            target = det.label[len(AGENT_LABEL) :]
            if target == self.config.agent_id or det.probability < MIN_FIX_CONFIDENCE:
                continue
            body = obs.pose @ det.pose
            ray = body[:2, 3] - obs.pose[:2, 3]  # from the camera to the robot, our frame
            try:
                cov = fix_covariance(float(np.linalg.norm(det.pose[:3, 3])), ray=ray)
            except ValueError as e:  # a detection's non-finite pose: that fix only is dropped
                log.warning("pose fix for %s not sent: %s", target, e)
                continue
            try:
                self.gossip.publisher.publish_fix(
                    target, body, cov, obs.time, det.object_id, det.probability
                )
            except Exception:
                log.exception("sending a pose fix to %s failed", target)

    def _apply_fixes(self, estimator: ScanEstimator) -> None:
        """Fuse the fixes received: each sender's frame into ours through the colony frame."""
        frame = self.colony_frame()
        later = []  # seen at a time this robot has not mapped yet (it is late): kept for then
        while self._fixes:
            msg = self._fixes.popleft()
            if estimator.localiser.ahead(msg.stamp):
                later.append(msg)
                continue
            me, framed = self.config.agent_id, estimator.framed
            own = fix_in_own_frame(
                frame,
                me,
                msg.origin,
                msg.matrix(),
                np.asarray(msg.covariance),
                alignment=not framed,
            )
            if own is None:
                self.metrics.add("fix_unaligned")
                self._sighted(estimator, msg)
                continue
            via = through(frame, me, msg.origin) if framed else None
            result = estimator.fix(own[0], own[1], msg.stamp, via)
            self.metrics.add(
                "fix_stale" if result is None else "fix_fused" if result else "fix_refused"
            )
        self._fixes.extend(later)

    def _apply_landmarks(self, estimator: ScanEstimator, obs: Observation) -> None:
        """Fuse the identified objects of `obs` that aligned peers know (paper Alg. 3)."""
        ids = {d.object_id for d in obs.objects}
        lists = {}
        for layer in self.layers.all():
            objects = [o for o in self.gossip.peer_objects.get(layer.origin) if o.object_id in ids]
            if objects:
                lists[layer.origin] = objects
        if lists:
            known = colony_landmarks(
                self.colony_frame(), self.config.agent_id, lists, framed=estimator.framed
            )
            estimator.landmarks(obs, known)

    def _sighted(self, estimator: ScanEstimator, msg: PoseFix) -> None:
        """A fix from an agent not aligned with us: keep it with our estimate at its stamp; once
        the sightings fit one transform (`frame_from_sightings`), offer it as an alignment."""
        then = estimator.localiser.pose_at(msg.stamp)
        if then is None or (
            msg.origin not in self._sightings and len(self._sightings) >= MAX_SIGHTED
        ):
            return
        kept = self._sightings.setdefault(msg.origin, deque(maxlen=50))
        kept.append((se2.from_matrix(msg.matrix()), then))
        fit = frame_from_sightings(np.array([a for a, _ in kept]), np.array([b for _, b in kept]))
        self.attempts[msg.origin] = {
            "aligned": fit.ok,
            "method": "sightings",
            "sightings": len(kept),
            "rmse_m": None if math.isinf(fit.rmse) else round(fit.rmse, 4),
            "reason": fit.reason,
            "time": time.time(),
        }
        if not fit.ok:
            return
        edge = Edge(
            self.config.agent_id,
            msg.origin,
            fit.transform,
            SIGHTING_CONFIDENCE,
            len(kept),
            fit.rmse,
            sightings_covariance(fit.rmse, fit.spread, np.array([b for _, b in kept])),
            time.time(),
        )
        self._offer(edge, f"from {len(kept)} sightings of us")
        kept.clear()

    # -- colony map (aligned peers' maps near the robot, for its scan matching) ------------
    def _colony_map_loop(self) -> None:
        """Give every scan estimator the aligned peers' map near its robot, in our frame."""
        while not self.stop.wait(self.config.colony_map_s):
            try:
                with self.metrics.activity.timed("colony-map"):
                    self._refresh_colony_maps()
            except Exception:
                log.exception("colony map refresh failed")

    def _refresh_colony_maps(self) -> None:
        pose = self.pose_matrix
        if pose is None:
            return
        frame = self.colony_frame()
        for spec, estimator in list(self._estimators.items()):
            if not isinstance(estimator, ScanEstimator):
                continue
            maps = self._colony_maps.get(spec)
            if maps is None:
                maps = self._colony_maps[spec] = ColonyMaps(
                    self.config.agent_id,
                    planar=estimator.planar,
                    height=estimator.height,
                    sensor_range=estimator.sensor_range,
                )
            poses = self.membership.pose_covariances() if self.config.colony_peer_pose else {}
            walks = self.membership.pose_drifts()
            estimator.colony = maps.refresh(self.layers, frame, pose, poses, walks)

    def _localisation_report(self) -> dict[str, Any]:
        out: dict[str, Any] = {"estimate_ms": round(self._estimate_s * 1000, 2)}
        for spec, estimator in list(self._estimators.items()):
            entry: dict[str, Any] = {"estimator": estimator.name}
            if isinstance(estimator, ScanEstimator):
                entry.update(estimator.counts())
                maps = self._colony_maps.get(spec)
                entry["colony_map"] = None if maps is None else maps.report()
            out[spec] = entry
        return out

    # -- alignment (own layer against each peer's, one pair per round) ---------------------
    def _align_loop(self) -> None:
        # peer -> own seq + its seq at our last attempt, and the object counts then: a pair is
        # tried again when either map grew or either object list changed (re-estimated as the
        # maps grow; a refused pair may be settled by more data or by objects).
        attempted: dict[str, tuple[int, tuple[int, int]]] = {}
        # peer -> an accepted estimate not offered yet. An estimate is offered once a later
        # attempt on grown maps accepts a pose that agrees with it, or once its maps stopped
        # growing (nothing new a round later); a refusal drops it. Partial maps can fit a wrong
        # place that more data refutes, and an offer cannot be taken back.
        pending: dict[str, tuple[Edge, int]] = {}
        refusals: dict[str, int] = {}  # peer -> refusals in a row since our offer
        rounds = 0
        while not self.stop.wait(self.config.align_s or SITE_OFFER_S):
            rounds += 1
            if rounds % OFFERS_REPEAT == 0:
                for edge in list(self._own_edges.values()):
                    self.gossip.publish_align(edge)
            if self.config.align_s == 0:
                continue  # registration off: only the surveyed pose is offered
            own = self.layers.own
            own_objects = list(self.objects.current)
            grown: dict[str, int] = {}
            for layer in self.layers.all():
                if layer.origin == own.origin or not layer.seq:
                    continue
                seqs, counts = attempted.get(layer.origin, (0, (-1, -1)))
                now = (len(own_objects), len(self.gossip.peer_objects.get(layer.origin)))
                grown[layer.origin] = own.seq + layer.seq - seqs + (1 if now != counts else 0)
            for origin, (edge, seqs) in list(pending.items()):
                if grown.get(origin, 1) <= 0 and attempted.get(origin, (None,))[0] == seqs:
                    del pending[origin]  # computed on maps that stopped growing: final
                    self._offer(edge, "final maps")
            if own.seq == 0 or not grown or max(grown.values()) <= 0:
                continue
            with self.metrics.activity.timed("bias"):
                self._estimate_bias()
            origin = max(grown, key=lambda o: (grown[o], o))  # the pair with most new data
            peer = self.layers.find(origin)
            if peer is None:
                continue
            peer_objects = self.gossip.peer_objects.get(origin)
            seqs = own.seq + peer.seq
            attempted[origin] = (seqs, (len(own_objects), len(peer_objects)))
            try:
                with self.metrics.activity.timed("align"):
                    result = align_layers(
                        own, peer, self.config.align_dof, own_objects, peer_objects, self.aligner
                    )
            except ValueError as exc:  # too little of a map to align yet
                self.attempts[peer.origin] = {"aligned": False, "reason": str(exc)}
                pending.pop(origin, None)
                continue
            except StoppedError:
                return
            except Exception:
                log.exception("alignment with %s failed", peer.origin)
                continue
            record = result.to_json()
            record["time"] = time.time()
            record["objects_used"] = {"own": len(own_objects), "peer": len(peer_objects)}
            self.attempts[peer.origin] = record
            if not result.aligned:
                pending.pop(origin, None)
                refusals[origin] = refusals.get(origin, 0) + 1
                if refusals[origin] >= WITHDRAW_AFTER:
                    self._withdraw(origin, refusals.pop(origin))
                continue
            refusals.pop(origin, None)
            before = pending.pop(origin, None)
            # how far the last estimate of this alignment was from this one: its scatter is
            # part of its error (frame_error.from_residuals)
            last = before[0] if before is not None else self._own_edges.get(origin)
            scatter = (
                None if last is None else frame_error.difference(last.transform, result.transform)
            )
            edge = edge_of(own.origin, peer.origin, result, scatter)
            if (
                before is not None
                and before[1] < seqs
                and _agree(before[0].transform, edge.transform)
            ):
                self._offer(edge, f"confirmed on grown maps ({result.method})")
            else:
                pending[origin] = (edge, seqs)
                record["provisional"] = True

    def _estimate_bias(self) -> None:
        """b from disagreement with the peers aligned in the colony frame (next records), at
        most every BIAS_S seconds (it reads whole layers)."""
        if time.monotonic() - self._bias_at < BIAS_S:
            return
        try:
            frame = self.colony_frame()
            if len(frame.transforms) < 2 or self.config.agent_id not in frame.transforms:
                return
            self._bias_at = time.monotonic()
            own = self.layers.own
            peers = [layer for layer in self.layers.all() if layer.origin != own.origin]
            bias = agent_bias(own, peers, frame.transforms)
        except Exception:
            log.exception("bias estimate failed")
            return
        if bias is not None:
            self.bias = bias

    def _offer(self, edge: Edge, why: str) -> None:
        if edge.target in self._own_edges and self._own_edges[edge.target].confidence >= 1.0:
            return  # a surveyed pose is not replaced by an estimate
        self._own_edges[edge.target] = edge
        self.gossip.publish_align(edge)
        log.info("aligned %s to our frame, %s: %s", edge.target, why, _pose_text(edge.transform))

    def _withdraw(self, peer: str, refused: int) -> None:
        """Take back our offer for `peer` (not a surveyed one): an offer of confidence 0."""
        edge = self._own_edges.get(peer)
        if edge is None or edge.confidence >= 1.0:
            return
        del self._own_edges[peer]
        self.gossip.publish_align(replace(edge, confidence=0.0, time=time.time()))
        log.warning("withdrew our alignment with %s: refused %d times in a row", peer, refused)

    def _weights(self) -> dict[str, float]:
        """Each layer's reliability weight in the fused map (`layer_weights`: agent or kind)."""
        kinds = {m.agent: m.kind for m in self.membership.table()}
        kinds[self.config.agent_id] = self.config.kind
        origins = [layer.origin for layer in self.layers.all()]
        return layer_weights(self.config.layer_weights, origins, kinds)

    def colony_frame(self) -> ColonyFrame:
        """The colony frame from every alignment known (own and offered)."""
        agents = [layer.origin for layer in self.layers.all()]
        return self.gossip.alignments.colony(agents, self.config.anchor)

    # -- ROS 2 outputs (map, cloud, objects when changed; the frame every round) -----------
    def _ros_loop(self) -> None:
        assert self.ros is not None
        last: tuple[Any, ...] = ()
        res, agent = self.config.resolution, self.config.agent_id
        while not self.stop.wait(self.config.ros2_period_s):
            try:
                frame = self.colony_frame()
                own = frame.transforms.get(agent, np.eye(4) if frame.root == agent else None)
                if own is not None:
                    self.metrics.add("ros2_bytes", self.ros.publish_frame(own))
                seen = (
                    tuple((layer.origin, layer.seq) for layer in self.layers.all()),
                    tuple((a, t.tobytes()) for a, t in sorted(frame.transforms.items())),
                    tuple(o.object_id for o in self.objects.current),
                )
                if seen == last:
                    continue
                last = seen
                layers = self.layers.all()
                out = self.fused_map.outputs(
                    layers, res, frame.transforms, self._weights(), classes=False
                )
                self.metrics.add(
                    "ros2_bytes", self.ros.publish_map(out.keys, out.logodds, res, out.points)
                )
                positions, ids = self._colony_objects(frame.transforms)
                self.metrics.add("ros2_bytes", self.ros.publish_objects(positions, ids, 4 * res))
                self.metrics.add("ros2_maps")
            except ValueError as exc:
                log.error("ROS 2 outputs: %s", exc)
            except Exception:
                log.exception("ROS 2 outputs failed")

    def _colony_objects(self, transforms: dict[str, np.ndarray]) -> tuple[np.ndarray, list[int]]:
        """Object centroids of every agent with a place in the colony frame, moved into it."""
        positions, ids = [], []
        agent = self.config.agent_id
        lists: list[tuple[str, list[tuple[int, Any]]]] = [
            (agent, [(o.object_id, o.position) for o in self.objects.current])
        ]
        lists += [
            (origin, [(o.object_id, o.position) for o in self.gossip.peer_objects.get(origin)])
            for origin in self.gossip.peer_objects.origins()
        ]
        for origin, objects in lists:
            t = transforms.get(origin)
            for object_id, position in objects:
                if t is not None:
                    positions.append(t[:3, :3] @ np.asarray(position, float) + t[:3, 3])
                    ids.append(int(object_id))
        return np.array(positions, float).reshape(-1, 3), ids

    # -- objects (own list refreshed and published when it changes) -----------------------
    def _objects_loop(self) -> None:
        """Refresh the own object list; publish it when it changed, and again every
        `OBJECTS_REPEAT` refreshes so that members that missed it (joined late, dropped a
        frame) get it too."""
        own = self.layers.own
        rounds = 0
        while not self.stop.wait(self.config.objects_s):
            try:
                with self.metrics.activity.timed("objects"):
                    changed = self.objects.refresh(own)
                rounds += 1
                if changed is not None or (self.objects.current and rounds % OBJECTS_REPEAT == 0):
                    self.gossip.publish_objects(to_wire(self.objects.current))
            except Exception:
                log.exception("object refresh failed")

    # -- publishing (own deltas, write-ahead logged, coalesced) ---------------------------
    def _publish_loop(self) -> None:
        nudge = self.layers.own.nudge  # a snapshot of the own layer waits for what is logged
        while not self.stop.is_set():
            nudge.wait(1.0 / self.config.publish_hz)
            nudge.clear()
            if self.stop.is_set():
                break
            try:
                with self.metrics.activity.timed("publish"):
                    self._publish_once()
            except PersistenceError as exc:
                self._state_failed(exc)
            except ColonydError as exc:
                log.error("publish failed: %s", exc)
            except Exception:
                log.exception("publish failed")

    def _forget_due(self) -> None:
        """Every `forget_s`, forget what decayed or aged out of the own layer (a new version:
        the next delta carries it to peers as unknown). Called with the layer's lock held, by
        the delta's extraction: no scan comes between the forget and the delta, so every voxel
        forgotten is unknown in it, and a recovery that applies it drops their history as the
        forget did (StateStore.recover)."""
        cfg = self.config
        if cfg.half_life_s is None and cfg.forget_after_s is None:
            return
        if time.monotonic() - self._last_forget < cfg.forget_s:
            return
        self._last_forget = time.monotonic()
        self.bias = 0.0  # b: this agent's bias against aligned peers (colonyd/provenance.py)
        self._bias_at = time.monotonic()
        freed = self.layers.own.grid.forget(after=cfg.forget_after_s)  # at the latest time
        if freed:
            self.metrics.add("blocks_forgotten", freed)

    def _publish_once(self, final: bool = False) -> None:
        """One publish step, one at a time: the final one at shutdown waits for one under way
        on the publisher thread (waited for 3 s only: a slow flush outlasts it), or both took
        the same seq and the log held two records of it (recovery keeps the first)."""
        with self._publishing:
            self._publish_step(final)

    def _publish_step(self, final: bool) -> None:
        own = self.layers.own
        with own.lock:
            self._forget_due()
            version = int(own.grid.version)
            delta = (
                own.grid.delta_since(self._published_local)
                if version != self._published_local
                else None
            )
            positions = self.positions.record()  # of exactly this version's frames
            # the history of the delta's versions, logged with it (a SIGKILL loses none)
            history = (
                own.grid.history.since(self._published_local, version)
                if delta is not None and len(delta)
                else None
            )
            captured = own.capture()  # the grid as logged, for a snapshot waiting for it
        wrote = unsynced = False
        if delta is not None and len(delta):
            created = time.time()
            marks: dict[str, float] = {}
            stamp(marks, "created")
            prev, seq = own.seq, own.seq + 1
            # Logged before anyone sees it; if the log cannot take it (disk full), nothing is
            # published and the same changes are tried again next time.
            try:
                if self.config.sync_before_publish or not self.store.early_publish:
                    # durable first (the frames are encoded while the disk flushes)
                    encoded = self.store.append(
                        seq,
                        delta,
                        meanwhile=lambda: self._encode_own(prev, seq, delta, created),
                        sources=positions,
                        history=history,
                        created=created,
                    )
                else:
                    # written (safe from a crash of this process), published, then flushed
                    # below: a reboot that loses it starts a new epoch (StateStore)
                    self.store.write(seq, delta, positions, history, created)
                    encoded, unsynced = None, True
            except PersistenceError as exc:
                own.log_failed(str(exc))  # a snapshot waiting for this delta gives up now
                raise
            wrote = True
            stamp(marks, "logged")
            self.gossip.publish_own(prev, seq, delta, created, encoded, marks)
            self.metrics.stage("out", self.config.agent_id, seq, marks)
            self.gossip.push_history(version)  # history push on: the records of what was sent
        if delta is not None:
            self._published_local = version
            with own.lock:
                own.grid.settle(version)  # forgotten voxels are in a logged, published delta
            own.mark_logged(version, captured)  # at own.seq: snapshots may hold it now
        if unsynced:
            with self.metrics.activity.timed("sync"):
                self.store.sync()
        due = time.monotonic() - self._last_snapshot >= self.config.snapshot_s
        if not final and own.seq > 0 and (due or self.store.wal_bytes > (64 << 20)):
            self._last_snapshot = time.monotonic()  # a failed one is retried after snapshot_s
            with self.metrics.activity.timed("snapshot"), own.lock:
                self.store.snapshot(
                    own.grid, own.seq, self._published_local, self.positions.record()
                )
            wrote = True
        if wrote and self.state_error:
            log.warning("state directory %s is writable again", self.config.state_dir)
            self.state_error = ""

    def _encode_own(self, prev: int, seq: int, delta: Delta, created: float) -> Any:
        """An own delta's frames, made while its record flushes; None if that fails: the record
        is logged all the same, so its seq is taken, and `publish_own` numbers the layer with it
        before it encodes again (the error propagated from the log's append, and the next delta
        was logged under the same seq: recovery kept the first record of it, and lost what only
        the second held)."""
        try:
            return self.gossip.encode_own(prev, seq, delta, created)
        except Exception:
            log.exception("encoding own delta seq %d failed; encoding it again to publish it", seq)
            return None

    def _state_failed(self, exc: PersistenceError) -> None:
        """A state-directory write failed: count it, say so (every 10 s at most), keep running."""
        self.metrics.add("state_errors")
        now = time.monotonic()
        if str(exc) != self.state_error or now - self._state_error_logged > 10.0:
            self._state_error_logged = now
            log.error(
                "%s; mapping and replicas go on, own deltas wait until the state "
                "directory takes writes again",
                exc,
            )
        self.state_error = str(exc)

    # -- export (a live map for `colonyd export`) -----------------------------------------
    def export_map(self, params: dict[str, str]) -> bytes | None:
        """The fused map in the colony frame, or with `layer=ID` that layer in its own frame;
        with `at=T` (seconds) as it was at time T, from the layers' history (then without
        classes, and at the voxels' centres: the history keeps no surfaces)."""
        agent = self.config.agent_id
        layer_id = params.get("layer")
        try:
            at = export_time(params.get("at"))
        except ValueError:
            return None
        if not layer_id:
            return encode_map(self.fused_reply(at))
        layer = self.layers.find(layer_id)
        if layer is None:
            return None
        res, frame = layer.resolution, frame_of(layer_id)
        if at is not None:
            keys, lo = layer.known_at(at)
            return encode_map(MapReply(agent, layer_id, frame, res, keys, lo))
        full = layer.full()
        known = ~np.isnan(full.logodds)
        keys, lo = full.keys[known], full.logodds[known]
        classes = best_class(full)[0][known]
        points = fused_surface([layer], res, keys[lo >= 0])
        return encode_map(MapReply(agent, layer_id, frame, res, keys, lo, [], classes, points))

    def fused_reply(self, at: float | None = None) -> MapReply:
        """The fused map in the colony frame with its layers' names, each voxel's class and
        the occupied voxels' surface points (`fused_surface`); with `at` (seconds), as it was
        then, from the layers' history (no classes, centres)."""
        frame, layers, res = self.colony_frame(), self.layers.all(), self.config.resolution
        names = sorted(frame.transforms)
        if at is not None:
            keys, lo = fused(layers, res, frame.transforms, self._weights(), at=at)
            return MapReply(self.config.agent_id, None, frame_of(frame.root), res, keys, lo, names)
        out = self.fused_map.outputs(layers, res, frame.transforms, self._weights())
        return MapReply(
            self.config.agent_id,
            None,
            frame_of(frame.root),
            res,
            out.keys,
            out.logodds,
            names,
            out.classes,
            out.points,
        )

    # -- forgetting an agent (`colonyd forget-agent`) -----------------------------------------
    def forget_request(self, params: dict[str, str]) -> dict[str, Any]:
        """Forget `agent=ID`'s layer colony-wide: checked against the colony key when one is
        configured (`t` within a minute, `auth` its HMAC), then a tombstone that heartbeats
        carry to every member."""
        cfg = self.config
        try:
            agent = forget_params(params, colony_key(cfg.colony_key), time.time())
        except ValueError as exc:
            self.metrics.reject("bad-forget")
            if (held := self._forget_log.allow("bad-forget")) is not None:  # anyone may ask
                log.warning("refused a forget request: %s%s", exc, held_text(held))
            return {"agent": cfg.agent_id, "forgotten": None, "error": str(exc)}
        if agent == cfg.agent_id:
            return {"agent": cfg.agent_id, "forgotten": None, "error": OWN_LAYER}
        new = self.layers.forget_agent(agent)
        if new:
            log.warning("forgot the layer of %s (forget-agent request)", agent)
            self.gossip.hb_now.set()  # tell the colony now
        return {"agent": cfg.agent_id, "forgotten": agent, "new": new}

    # -- status ---------------------------------------------------------------------------
    def _colony_report(self) -> dict[str, Any]:
        frame = self.colony_frame()
        return {
            "root": frame.root,
            "agents": {a: np.round(t, 6).tolist() for a, t in sorted(frame.transforms.items())},
        }

    def report(self, params: dict[str, str]) -> dict[str, Any]:
        want_digest = params.get("digest") == "1"
        layers = {}
        for layer in self.layers.all():
            if layer.seq == 0 and layer.origin != self.config.agent_id:
                continue
            entry: dict[str, Any] = {
                "epoch": layer.epoch,
                "seq": layer.seq,
                "voxels": layer.voxels(),
                "updated": layer.updated,
                "pending": len(layer.pending),
                "half_life": layer.half_life,
                "history": layer.grid.history.size,
                "channels": sorted(layer.grid.store.channels),
            }
            if want_digest:
                entry["digest"] = layer.digest()
            layers[layer.origin] = entry
        own = self.layers.own
        with own.lock:
            unpublished = int(own.grid.version) != self._published_local
        return {
            "agent": self.config.agent_id,
            "kind": self.config.kind,
            "colony": self.config.colony,
            "epoch": self.epoch,
            "pid": os.getpid(),
            "time": time.time(),
            "uptime": time.time() - self.started,
            "pose": self.pose,
            "pose_error_m": self.pose_error.last,
            "pose_covariance": None
            if self.pose_covariance is None
            else np.round(self.pose_covariance, 9).tolist(),
            "localisation": self._localisation_report(),
            "pose_matrix": None if self.pose_matrix is None else self.pose_matrix.tolist(),
            "truth_matrix": None if self.truth_matrix is None else self.truth_matrix.tolist(),
            "sources_done": self._sources_done.is_set() or not self.config.sources,
            "warm": self.warm.is_set(),
            "heap_freezes": self.freezer.count,
            "sources": [
                {
                    "spec": s.spec,
                    "delivered": s.stats.delivered,
                    "skipped": s.stats.skipped,
                    "reasons": dict(s.stats.reasons),
                    **self._position_report(s.spec),
                    **({"received": dict(s.received)} if hasattr(s, "received") else {}),
                }
                for s in getattr(self, "_sources", [])
            ],
            "unpublished": unpublished,
            "frame": frame_of(self.config.agent_id),
            "colony_frame": self._colony_report(),
            "alignments": self.attempts,
            "state_error": self.state_error,
            "layers": layers,
            "objects": [
                {
                    "id": o.object_id,
                    "class": o.class_id,
                    "position": [float(x) for x in o.position],
                    "voxels": o.voxel_count,
                }
                for o in self.objects.current
            ],
            "peer_objects": {
                origin: [
                    {"id": o.object_id, "class": o.class_id, "position": list(o.position)}
                    for o in self.gossip.peer_objects.get(origin)
                ]
                for origin in self.gossip.peer_objects.origins()
            },
            "members": [
                {
                    "agent": m.agent,
                    "alive": m.alive,
                    "kind": m.kind,
                    "last_seen": m.last_seen,
                    "pose": m.pose,
                    "pose_std_m": m.pose_std_m,
                    "layers": {o: list(v) for o, v in m.layers.items()},
                }
                for m in self.membership.table()
            ],
            "metrics": self.metrics.snapshot(samples=params.get("samples") == "1"),
        }

    def _position_report(self, spec: str) -> dict[str, Any]:
        """A recording's position in the status: frames in the layer, those passed over at
        start (already in the recovered layer), and whether it was read to its end."""
        positions: Positions | None = getattr(self, "positions", None)
        p = None if positions is None else positions.position(spec)
        if positions is None or p is None:
            return {}
        return {
            "position": p.frames,
            "resumed_after": positions.resumed.get(spec, 0),
            "done": p.done,
        }


def _pose_text(t: Any) -> str:
    yaw = math.degrees(math.atan2(t[1, 0], t[0, 0]))
    return f"x {t[0, 3]:.2f} y {t[1, 3]:.2f} z {t[2, 3]:.2f} m, yaw {yaw:.1f} deg"


def member_table(
    session: zenoh.Session, cfg: Config, on_event: Callable[[str, str], None]
) -> Membership:
    """The daemon's member table (liveliness and heartbeats): `max_members` members heard,
    whatever `max_layers` (members that hold no layer, cameras or command-line clients, keep no
    robot out), each remembered to hold at most `max_layers` + 1 layers (what this daemon could
    hold of them: the bound on the table's memory)."""
    return Membership(
        session,
        cfg.key_namespace,
        cfg.agent_id,
        on_event,
        cfg.max_members,
        max_listed=cfg.max_layers + 1,
    )


def run_daemon(
    config: Config, config_path: Path | None = None, flags: dict[str, Any] | None = None
) -> int:
    """Run until SIGTERM/SIGINT; returns the exit code."""
    setup_logging(config.log_level, agent=config.agent_id)
    # A thread waiting for the GIL (a Zenoh callback, the inbox, the publisher) gets it within
    # 1 ms instead of 5 while mapping holds it: the latency of gossip under load.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    return Daemon(config, config_path, flags).run()


class _Laps:
    """Appends (step, time now) to a list: how long each shutdown step took, for the log."""

    def __init__(self, laps: list[tuple[str, float]]) -> None:
        self.laps = laps

    def __call__(self, step: str) -> None:
        self.laps.append((step, time.monotonic()))


def _agree(t1: np.ndarray, t2: np.ndarray, metres: float = 0.25, degrees: float = 2.0) -> bool:
    """Two estimates of one alignment are the same pose (within `metres` and `degrees`)."""
    d = np.linalg.inv(t1) @ t2
    yaw = abs(math.degrees(math.atan2(d[1, 0], d[0, 0])))
    return float(np.linalg.norm(d[:3, 3])) <= metres and yaw <= degrees
