"""Extended Kalman filter over a planar pose (x, y, yaw) with filterpy: odometry predicts, pose
measurements update; the errors of the agent's keyframes and of a shared map are estimated with
the pose."""

from __future__ import annotations

import functools
import math
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np

from voxel.errors import LocalisationError
from voxel.localisation import frame_error, se2

#: Chi-square 99.9 % quantile with 3 degrees of freedom: a pose measurement farther than this
#: (Mahalanobis distance squared) from the prediction is rejected as an outlier.
GATE_3DOF = 16.27
#: The same with 2 degrees of freedom: a landmark's position seen in the body frame.
GATE_2DOF = 13.82
#: Landmarks whose error the filter estimates at most (`update_landmark` with a key): beyond it
#: the least recently seen is dropped (marginalised: its rows leave the state).
MAX_LANDMARKS = 16
#: Frames whose error the filter estimates at most (`reset_frame`): the colony map's offset and
#: one per origin whose fixes or landmarks come through an alignment; beyond it the least
#: recently used is dropped (marginalised).
MAX_FRAMES = 8
#: The key of the colony map's offset among the frames (`reset_offset` and the rest).
COLONY = "colony map"


@dataclass(frozen=True)
class MotionNoise:
    """What the filter assumes about odometry: random-walk standard deviations, as in the odometry
    model.

    Deliberately not the simulator's true parameters: a filter is tuned to a robot class, not to
    one seeded run. The biases of real odometry are not modelled, so these are generous.
    """

    trans: float = 0.1  # m per sqrt(m)
    rot: float = 0.1  # rad per sqrt(rad)
    rot_per_m: float = 0.03  # rad per sqrt(m)
    still: float = 1e-4  # variance floor per step (m^2, rad^2)
    no_odometry: float = 0.3  # standard deviation per step (m, rad) when there is no odometry


def _residual(z: np.ndarray, hx: np.ndarray) -> np.ndarray:
    y: np.ndarray = z - hx
    y[2] = se2.wrap(float(y[2, 0]))
    return y


def _import_kalman() -> Any:
    """filterpy.kalman, imported without scipy.stats and scipy.ndimage.

    Importing filterpy imports all of it: its filters import `logpdf` from filterpy.stats, which
    imports scipy.stats, and filterpy.discrete_bayes imports scipy.ndimage: ~1 s of CPU at the
    start of every process with a filter (measured: importing filterpy.kalman takes 1.6-1.7 s of
    CPU, 0.75 without), for a likelihood this filter never computes (its updates are its own,
    `PlanarEkf._fuse`) and a filter it does not use. While filterpy is imported, those two are
    stand-ins (filterpy.stats's `logpdf`, the only name filterpy.kalman takes from it, imports
    the real one when first called); they leave sys.modules before this returns, so any later
    import of them gets the real modules."""
    import importlib
    import sys
    import types

    if "filterpy" in sys.modules:
        return importlib.import_module("filterpy.kalman")

    def logpdf(*args: Any, **kwargs: Any) -> Any:
        return importlib.import_module("filterpy.stats").logpdf(*args, **kwargs)

    stand_ins = {
        name: types.ModuleType(name, "stands in while filterpy is imported")
        for name in ("filterpy.stats", "filterpy.discrete_bayes")
    }
    stand_ins["filterpy.stats"].logpdf = logpdf  # type: ignore[attr-defined]
    sys.modules.update(stand_ins)
    try:
        return importlib.import_module("filterpy.kalman")
    finally:
        parent = sys.modules.get("filterpy")
        for name, module in stand_ins.items():
            if sys.modules.get(name) is module:
                del sys.modules[name]
            if parent is not None and getattr(parent, name.split(".")[1], None) is module:
                delattr(parent, name.split(".")[1])


@functools.cache
def _filter_class() -> Any:
    """filterpy's EKF with the nonlinear planar motion model as its state prediction.

    Imported on first use, without scipy.stats (`_import_kalman`)."""
    base: Any = _import_kalman().ExtendedKalmanFilter

    class _Filter(base):  # type: ignore[misc]  # filterpy has no type hints
        x: np.ndarray  # the state (3, 1), as filterpy keeps it

        def predict_x(self, u: np.ndarray) -> None:
            self.x = se2.compose(self.x.ravel(), u).reshape(3, 1)

    return _Filter


@dataclass
class Offset:
    """The error of a map the pose is measured against (a colony map: a peer's surfaces put into
    this agent's frame by an alignment), estimated with the pose: a small motion (x, y, yaw)
    about the agent's origin, its covariance and its cross-covariance with the pose, and the
    prior covariance accounted for so far (`reset_offset`'s, grown by `widen_offset`)."""

    value: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)
    cross: np.ndarray  # (3, 3): cov(pose, offset)
    accounted: np.ndarray  # (3, 3)


@dataclass
class _Frame:
    """A frame whose error the filter estimates (`reset_frame`): its key, the prior covariance
    accounted for so far (3, 3), when it was last reset and last used (the filter's count of
    frame uses: a reset is unique to that frame's error)."""

    key: Hashable
    accounted: np.ndarray
    resets: int
    used: int


@dataclass
class _Landmark:
    """A landmark whose error the filter estimates: its id, the position published at its last
    sighting (2,), the prior covariance of its error accounted for so far (2, 2), when it was
    last seen (the filter's count of landmark updates), and the frame it came through then
    (its key and that frame's resets; None: none)."""

    key: int
    published: np.ndarray
    accounted: np.ndarray
    seen: int
    through: tuple[Hashable, int] | None = None


class PlanarEkf:
    """Pose (x, y, yaw) and covariance of one ground agent, with the errors of what it is
    measured against.

    **Keyframes** (`add_keyframe`): the agent's own map is built from its estimate, so a match
    against it measures the pose relative to the poses the map's keyframes were placed at, not
    in the world: the map's error is the estimate's error when those keyframes were taken. Each
    keyframe's error (a small correction (x, y, yaw) of the pose it was placed at) is part of
    the state, entering with the pose's covariance and fully correlated with the pose; odometry
    then decorrelates them. A match against recent keyframes measures only the error grown
    since (`update_relative`): the covariance keeps growing like odometry's, and shrinks only
    when the match reaches keyframes that are better known than the present (a loop closure).
    An absolute measurement (`update`, `update_landmark`, `update_offset`) also corrects the
    keyframes in proportion to their correlation with the pose: recent keyframes move with the
    pose, so the own map does not pull a correct fix back.

    **Frames** (`reset_frame`): the error of a frame measurements come through, keyed. Every
    match against a shared map shares the alignment's error, and so does every fix or landmark
    put into this agent's frame by one alignment, so fusing them as independent measurements
    would count the alignment once per measurement and carry the robot into the alignment's
    error. Estimated as part of the state, the alignment's error is counted once: however many
    measurements come through a poor alignment, they move the pose no more than its covariance
    against the pose's allows. The frame's error may grow after the reset (its peer drifts or
    gets lost): `widen_frame` adds the growth as process noise. The colony map's is the frame
    `COLONY` (`reset_offset`, `update_offset` and the rest, its **Offset**).
    """

    def __init__(
        self,
        pose: np.ndarray,
        covariance: np.ndarray | None = None,
        motion: MotionNoise | None = None,
    ) -> None:
        self.motion = motion or MotionNoise()
        self.kf = _filter_class()(dim_x=3, dim_z=3)
        self.kf.x = np.asarray(pose, np.float64).reshape(3, 1).copy()
        self.kf.P = (
            np.diag([1e-6, 1e-6, 1e-6])
            if covariance is None
            else np.asarray(covariance, np.float64).copy()
        )
        self.accepted = self.rejected = 0
        # The rest of the state: 3 per frame (first), then 3 per keyframe, then 2 per landmark
        # (its error: published minus true position, x and y).
        self._mean = np.zeros(0)  # (m,)
        self._cov = np.zeros((0, 0))  # (m, m)
        self._cross = np.zeros((3, 0))  # (3, m): cov(pose, rest)
        #: Per frame whose error is estimated, in the state's order.
        self._frames: list[_Frame] = []
        self._frame_clock = 0
        self.max_frames = MAX_FRAMES
        self._keys: list[int] = []
        self._key_poses: list[np.ndarray] = []  # the pose each keyframe was placed at
        #: Per landmark whose error is estimated, in the state's order.
        self._landmarks: list[_Landmark] = []
        self._landmark_clock = 0  # keyed landmark updates so far (when each was last seen)
        self.max_landmarks = MAX_LANDMARKS

    @property
    def pose(self) -> np.ndarray:
        """Current (x, y, yaw)."""
        pose: np.ndarray = self.kf.x.ravel().copy()
        return pose

    @property
    def covariance(self) -> np.ndarray:
        """Current 3x3 covariance."""
        covariance: np.ndarray = self.kf.P.copy()
        return covariance

    @property
    def offset(self) -> Offset | None:
        """The shared map's error (a copy), once `reset_offset` started estimating it."""
        return self.frame(COLONY)

    @property
    def frames(self) -> list[Hashable]:
        """Keys of the frames whose errors are estimated, in the state's order."""
        return [f.key for f in self._frames]

    def frame(self, key: Hashable) -> Offset | None:
        """Frame `key`'s error (a copy, as `Offset`), None when it is not estimated."""
        i = self._frame_index(key)
        if i is None:
            return None
        k = self._frame_slice(i)
        return Offset(
            self._mean[k].copy(),
            self._cov[k, k].copy(),
            self._cross[:, k].copy(),
            self._frames[i].accounted.copy(),
        )

    def _frame_index(self, key: Hashable) -> int | None:
        for i, f in enumerate(self._frames):
            if f.key == key:
                return i
        return None

    def _frame_slice(self, i: int) -> slice:
        return slice(3 * i, 3 * i + 3)

    def _used(self, key: Hashable, what: str) -> tuple[int, slice]:
        """Frame `key`'s index and rows, marked as used now; an error naming `what` when the
        frame is not estimated."""
        i = self._frame_index(key)
        if i is None:
            call = "reset_offset" if key == COLONY else "reset_frame"
            msg = f"{what}: expected {call}() first (frame {key!r} is not estimated)"
            raise LocalisationError(msg)
        self._frame_clock += 1
        self._frames[i].used = self._frame_clock
        return i, self._frame_slice(i)

    @property
    def keyframes(self) -> list[int]:
        """Ids of the keyframes whose errors are estimated, oldest first."""
        return list(self._keys)

    def keyframe(self, key: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A keyframe's pose as placed, its estimated error (a correction of that pose) and the
        error's covariance."""
        i = self._keys.index(key)
        k = self._key_slice(i)
        return self._key_poses[i].copy(), self._mean[k].copy(), self._cov[k, k].copy()

    def seen_from(self, key: int) -> np.ndarray:
        """Where the current pose appears in keyframe `key`'s map (placed with the error the
        filter now estimates for it)."""
        i = self._keys.index(key)
        placed = self._key_poses[i][None]
        seen, _, _ = _seen_from(placed, self._mean[self._key_slice(i)][None], self.pose)
        out: np.ndarray = seen[0]
        return out

    def _key_slice(self, i: int) -> slice:
        first = 3 * len(self._frames) + 3 * i
        return slice(first, first + 3)

    @property
    def _poses_end(self) -> int:
        """Where the 3-wide blocks (frames, keyframes) end and the landmarks' 2-wide begin."""
        return 3 * (len(self._frames) + len(self._keys))

    def _landmark_slice(self, i: int) -> slice:
        first = self._poses_end + 2 * i
        return slice(first, first + 2)

    def _insert(
        self, at: int, mean: np.ndarray, cov: np.ndarray, with_pose: np.ndarray | None = None
    ) -> None:
        """Insert a block of the state at row `at`: its mean (k,) and covariance (k, k), and
        with `with_pose` the pose's own error (its covariance with the pose is the pose's
        covariance (3, k), with the rest the pose's); without, uncorrelated with everything."""
        k = len(mean)
        x = self._cross
        if with_pose is None:
            with_pose, with_rest = np.zeros((3, k)), np.zeros((len(self._mean), k))
        else:
            with_rest = x.T
        c = self._cov
        self._mean = np.concatenate([self._mean[:at], mean, self._mean[at:]])
        self._cov = np.block(
            [
                [c[:at, :at], with_rest[:at], c[:at, at:]],
                [with_rest[:at].T, cov, with_rest[at:].T],
                [c[at:, :at], with_rest[at:], c[at:, at:]],
            ]
        )
        self._cross = np.hstack([x[:, :at], with_pose, x[:, at:]])

    def _remove(self, rows: np.ndarray) -> None:
        """Drop rows of the state (marginalise them out: a Gaussian's other rows keep their
        mean and covariance)."""
        keep = np.setdiff1d(np.arange(len(self._mean)), rows)
        self._mean = self._mean[keep]
        self._cov = self._cov[np.ix_(keep, keep)]
        self._cross = self._cross[:, keep]

    def add_keyframe(self, key: int) -> None:
        """Start estimating the error of a keyframe placed at the current pose: the pose's
        error, so its covariance and correlations are the pose's."""
        p = self.kf.P
        self._insert(self._poses_end, np.zeros(3), p.copy(), p)
        self._keys.append(int(key))
        self._key_poses.append(self.pose)

    def keep_keyframes(self, keys: list[int]) -> None:
        """Stop estimating the errors of keyframes not in `keys` (the map dropped them)."""
        wanted = set(keys)
        drop = [i for i, k in enumerate(self._keys) if k not in wanted]
        if not drop:
            return
        rows = np.concatenate(
            [np.arange(self._key_slice(i).start, self._key_slice(i).stop) for i in drop]
        )
        self._remove(rows)
        self._keys = [k for i, k in enumerate(self._keys) if i not in drop]
        self._key_poses = [p for i, p in enumerate(self._key_poses) if i not in drop]

    def motion_step(self, increment: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The motion `predict` applies for an odometry increment (None: none) and its
        covariance in the body frame (the motion model's)."""
        m = self.motion
        if increment is None:
            return np.zeros(3), np.diag([m.no_odometry**2] * 3)
        u = np.asarray(increment, np.float64)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            msg = f"odometry increment: expected 3 finite numbers (dx, dy, dyaw), found {u}"
            raise LocalisationError(msg)
        d = math.hypot(u[0], u[1])
        var_t = m.trans**2 * d + m.still
        q_u = np.diag([var_t, var_t, m.rot**2 * abs(u[2]) + m.rot_per_m**2 * d + m.still])
        return u, q_u

    def predict(self, increment: np.ndarray | None) -> None:
        """Move by an odometry increment (dx, dy, dyaw) in the body frame; None: no odometry (stand
        still, widen)."""
        u, q_u = self.motion_step(increment)
        yaw = float(self.kf.x[2, 0])
        c, s = math.cos(yaw), math.sin(yaw)
        self.kf.F = np.array(
            [[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0.0, 0.0, 1.0]]
        )
        g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.kf.Q = g @ q_u @ g.T
        self.kf.predict(u)
        self._cross = self.kf.F @ self._cross

    def innovation(self, pose: np.ndarray, covariance: np.ndarray) -> float:
        """Squared Mahalanobis distance of an absolute pose measurement from the prediction."""
        y = _residual(np.asarray(pose, np.float64).reshape(3, 1), self.kf.x.copy())
        s = self.kf.P + covariance
        return float((y.T @ np.linalg.solve(s, y))[0, 0])

    def update(
        self, pose: np.ndarray, covariance: np.ndarray, gate: float | None = GATE_3DOF
    ) -> bool:
        """Fuse an absolute measured pose (x, y, yaw) with its covariance; False (and no change)
        when gated out."""
        z, r = checked_pose(pose, covariance)
        y = _residual(z.reshape(3, 1), self.kf.x.copy()).ravel()
        return self._fuse(np.eye(3), None, y, r, gate)

    def update_relative(
        self,
        pose: np.ndarray,
        covariance: np.ndarray,
        keys: np.ndarray,
        information: np.ndarray,
        gate: float | None = GATE_3DOF,
    ) -> bool:
        """Fuse a pose (x, y, yaw) matched against the agent's own map, whose correspondences
        came from keyframes `keys` (G,), each giving `information` (G, 3, 3) of the match (its
        pairs' share of the Hessian). The map near the agent is each keyframe's points placed
        by that keyframe's pose, so the match measures the pose moved by the keyframes' errors,
        each weighted by its share of the information. A keyframe the filter does not know
        counts as placed without error. False (and no change) when gated out."""
        z, r = checked_pose(pose, covariance)
        keys = np.asarray(keys).reshape(-1)
        info = np.asarray(information, np.float64).reshape(len(keys), 3, 3)
        total = info.sum(axis=0) + 1e-9 * np.eye(3)
        x = self.pose
        predicted = np.zeros(3)  # sum of the weighted moves of the pose by the keyframes
        h_pose = np.zeros((3, 3))
        h_rest = np.zeros((3, len(self._mean)))
        weights = np.linalg.solve(total[None], info)  # (G, 3, 3): each keyframe's in the match
        index = {k: i for i, k in enumerate(self._keys)}
        where = np.array([index.get(int(k), -1) for k in keys.tolist()], np.int64)
        known = where >= 0
        h_pose += weights[~known].sum(axis=0)  # unknown keyframes: placed without error
        if np.any(known):
            w, i = weights[known], where[known]
            first = 3 * len(self._frames)
            errors = self._mean[first : self._poses_end].reshape(-1, 3)[i]
            moved, d_pose, d_key = _seen_from(np.array(self._key_poses)[i], errors, x)
            step = moved - x
            step[:, 2] = (step[:, 2] + math.pi) % (2 * math.pi) - math.pi
            predicted = np.einsum("gij,gj->i", w, step)
            h_pose += np.einsum("gij,gjk->ik", w, d_pose)
            cols = first + 3 * i[:, None] + np.arange(3)  # (G', 3)
            h_rest[:, cols.ravel()] = np.einsum("gij,gjk->igk", w, d_key).reshape(3, -1)
        y = z - x - predicted
        y[2] = se2.wrap(float(y[2]))
        return self._fuse(h_pose, h_rest, y, r, gate)

    @property
    def landmarks(self) -> list[int]:
        """Ids of the landmarks whose errors are estimated, in the state's order."""
        return [lm.key for lm in self._landmarks]

    def landmark(self, key: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A landmark's position as last published, its estimated error (published minus true
        position, x and y) and the error's covariance (2x2)."""
        i = self.landmarks.index(key)
        k = self._landmark_slice(i)
        return self._landmarks[i].published.copy(), self._mean[k].copy(), self._cov[k, k].copy()

    def update_landmark(
        self,
        seen: np.ndarray,
        seen_covariance: np.ndarray,
        landmark: np.ndarray,
        landmark_covariance: np.ndarray,
        gate: float | None = GATE_2DOF,
        key: int | None = None,
        frame: Hashable | None = None,
    ) -> bool:
        """Fuse a landmark (paper Alg. 3): an object whose position (x, y) `landmark` in this
        agent's frame is known with `landmark_covariance` (2x2), seen at `seen` (x, y) in the
        body frame with `seen_covariance` (2x2). The measurement is R(yaw)^T (true position -
        position). False (and the pose unchanged) when gated out.

        Without `key`, the published position is taken as the true one and its covariance added
        to the sighting's: every sighting is an independent measurement, so N sightings count
        the published position's error N times. With `key` (the landmark's id), the error e
        (published minus true, x and y) is part of the state, counted once: at the first
        sighting it enters with mean zero and `landmark_covariance`, uncorrelated with the rest
        (a first sighting gated out leaves nothing); each sighting then measures R(yaw)^T
        (landmark - e - position) with its own noise alone, correcting pose and e together, so
        however many sightings share a wrong published position they move the pose no more
        than its covariance against the pose's allows. A published position that moved since
        the last sighting (the peer refined it, or the alignment changed) is the same truth: e's
        mean shifts by the move. A published covariance grown beyond what is accounted for
        widens e by the positive part of the growth (as `widen_offset`: a smaller one is no
        evidence, only a measurement shrinks it). At most `max_landmarks` are kept: a new one
        beyond drops the least recently seen (marginalised out; it re-enters with its
        published prior if seen again, counted a second time: the bound should exceed the
        landmarks in use). A landmark unseen for long is kept: its error is as valid as when
        it was last seen, and the bound caps the state.

        With `frame` (`reset_frame` first), `landmark` came into this agent's frame through
        that frame's alignment, whose error the filter estimates (shared by every landmark and
        fix through it): the true position is the published one moved back by the frame's
        error b, b^-1(landmark) (- e with `key`), and `landmark_covariance` is the landmark's
        own error alone, without the alignment's. A keyed landmark whose frame was reset since
        its last sighting (a new alignment) moved with the alignment, not the truth: e's mean
        stays."""
        z, r_seen, lm, r_lm = _checked_landmark(
            seen, seen_covariance, landmark, landmark_covariance
        )
        x = self.kf.x.ravel()
        c, s = math.cos(x[2]), math.sin(x[2])
        rt = np.array([[c, s], [-s, c]])  # world -> body
        h_rest = np.zeros((2, len(self._mean)))
        through: tuple[Hashable, int] | None = None
        true = lm  # the true position the filter estimates, before the landmark's own error
        if frame is not None:
            fi, frows = self._used(frame, f"landmark through frame {frame!r}")
            through = (frame, self._frames[fi].resets)
            b = self._mean[frows]
            cb, sb = math.cos(b[2]), math.sin(b[2])
            true = np.array([[cb, sb], [-sb, cb]]) @ (lm - b[:2])  # b^-1(landmark)
            d_b = np.zeros((2, 3))  # of b^-1(landmark) by b
            d_b[:, :2] = -np.array([[cb, sb], [-sb, cb]])
            d_b[:, 2] = (true[1], -true[0])
            h_rest[:, frows] = rt @ d_b
        if key is None:
            d = true - x[:2]
            jac = _landmark_jacobian(rt, d, c, s)
            hr = None if frame is None else h_rest
            return self._fuse(jac, hr, z - rt @ d, r_seen + rt @ r_lm @ rt.T, gate)
        new = int(key) not in self.landmarks
        if new:
            self._insert(len(self._mean), np.zeros(2), r_lm)
            h_rest = np.hstack([h_rest, np.zeros((2, 2))])
            self._landmarks.append(_Landmark(int(key), lm, r_lm, 0, through))
        i = self.landmarks.index(int(key))
        rows = self._landmark_slice(i)
        entry = self._landmarks[i]
        if entry.through == through:  # the same truth, published elsewhere
            self._mean[rows] += lm - entry.published
        grown = r_lm - entry.accounted
        w, v = np.linalg.eigh(0.5 * (grown + grown.T))
        q = (v * np.maximum(w, 0.0)) @ v.T  # the positive part of the growth
        self._cov[rows, rows] += q
        entry.published, entry.accounted, entry.through = lm, entry.accounted + q, through
        d = true - self._mean[rows] - x[:2]  # to the true position the filter estimates
        jac = _landmark_jacobian(rt, d, c, s)
        h_rest[:, rows] = -rt
        fused = self._fuse(jac, h_rest, z - rt @ d, r_seen, gate)
        self._landmark_clock += 1
        entry.seen = self._landmark_clock
        if new and not fused:
            self._drop_landmark(i)
        elif new and len(self._landmarks) > self.max_landmarks:
            self._drop_landmark(min(range(len(self._landmarks)), key=self._seen_at))
        return fused

    def _seen_at(self, i: int) -> int:
        return self._landmarks[i].seen

    def _drop_landmark(self, i: int) -> None:
        rows = self._landmark_slice(i)
        self._remove(np.arange(rows.start, rows.stop))
        del self._landmarks[i]

    def _fuse(
        self,
        h_pose: np.ndarray,
        h_rest: np.ndarray | None,
        y: np.ndarray,
        noise: np.ndarray,
        gate: float | None,
    ) -> bool:
        """A measurement of the state (Jacobians `h_pose` (k, 3) and `h_rest` (k, m), None:
        of the pose alone; innovation `y` (k,), noise (k, k)): gated, then fused into the
        pose, the offset and the keyframes' errors together."""
        p, cross, rest = self.kf.P, self._cross, self._cov
        m = len(self._mean)
        hr = np.zeros((len(y), m)) if h_rest is None else h_rest
        ph_pose = p @ h_pose.T + cross @ hr.T  # (3, k): cov(pose, measurement)
        ph_rest = cross.T @ h_pose.T + rest @ hr.T  # (m, k)
        innov = h_pose @ ph_pose + hr @ ph_rest + noise
        innov = 0.5 * (innov + innov.T)
        if gate is not None and float(y @ np.linalg.solve(innov, y)) > gate:
            self.rejected += 1
            return False
        si = np.linalg.inv(innov)
        k_pose, k_rest = ph_pose @ si, ph_rest @ si
        x = self.kf.x.ravel() + k_pose @ y
        x[2] = se2.wrap(float(x[2]))
        self.kf.x = x.reshape(3, 1)
        new_p = p - k_pose @ ph_pose.T
        self.kf.P = 0.5 * (new_p + new_p.T)
        if m:
            self._mean = self._mean + k_rest @ y
            self._cross = cross - k_pose @ ph_rest.T
            new_rest = rest - k_rest @ ph_rest.T
            self._cov = 0.5 * (new_rest + new_rest.T)
            end = self._poses_end  # every 3-wide block's yaw, wrapped as se2.wrap does
            yaws = self._mean[2:end:3]
            self._mean[2:end:3] = np.remainder(yaws + math.pi, 2.0 * math.pi) - math.pi
        self.accepted += 1
        return True

    def reset_frame(self, key: Hashable, covariance: np.ndarray) -> None:
        """Start estimating a new error of frame `key` (an alignment measurements come through,
        changed or first seen): zero, with `covariance` (x, y, yaw about the origin: the
        alignment's), uncorrelated with the pose and the rest of the state. Beyond
        `max_frames` the least recently used other frame is dropped (marginalised out)."""
        c = _checked_covariance(covariance, "offset" if key == COLONY else f"frame {key!r}")
        i = self._frame_index(key)
        if i is None:
            i = len(self._frames)
            self._insert(3 * i, np.zeros(3), np.zeros((3, 3)))
            self._frames.append(_Frame(key, c.copy(), 0, 0))
            if len(self._frames) > self.max_frames:
                others = [j for j in range(len(self._frames)) if j != i]
                oldest = min(others, key=lambda j: self._frames[j].used)
                self._remove(np.arange(3 * oldest, 3 * oldest + 3))
                del self._frames[oldest]
                i = self._frame_index(key)
                assert i is not None
        rows = self._frame_slice(i)
        self._mean[rows] = 0.0
        self._cov[rows, :] = 0.0
        self._cov[:, rows] = 0.0
        self._cov[rows, rows] = c
        self._cross[:, rows] = 0.0
        f = self._frames[i]
        self._frame_clock += 1
        f.accounted, f.resets, f.used = c.copy(), self._frame_clock, self._frame_clock

    def widen_frame(self, key: Hashable, covariance: np.ndarray) -> np.ndarray:
        """Frame `key`'s error now has the prior `covariance` (x, y, yaw about the origin), as
        its sources say today (a peer that drifted or got lost since `reset_frame`): add, as
        process noise, its growth beyond what is accounted for, and return that noise (3x3).

        The frame's error is modelled as a random walk: b' = b + w, w independent of everything
        else, so the frame's mean and its correlations with the rest stay and its covariance
        gains cov(w) = Q. Q is `covariance` minus the prior accounted for so far, where that is
        positive semi-definite; otherwise its positive part (the directions in which the error
        grew; an eigenvalue below zero is a source more certain than before, which is no
        evidence that the frame here improved: only a measurement shrinks the filter's
        covariance). What the filter learnt from measurements is kept: it only widens."""
        what = "offset widening" if key == COLONY else f"frame {key!r} widening"
        c = _checked_covariance(covariance, what)  # (checked before the frame counts as used)
        i, rows = self._used(key, what)
        f = self._frames[i]
        if np.array_equal(c, f.accounted):
            return np.zeros((3, 3))
        q = frame_error.positive(c - f.accounted)
        self._cov[rows, rows] += q
        f.accounted = f.accounted + q
        return q

    def walk_frame(self, key: Hashable, noise: np.ndarray, about: np.ndarray) -> np.ndarray:
        """Let frame `key`'s error wander: add `noise` (3x3: x, y and yaw of a small motion about
        the point `about` (x, y) of the agent's frame, where the agent now is) to it as process
        noise, and return it as the frame's (x, y, yaw about the origin).

        A random walk as in `widen_frame` (b' = b + w; the mean and the correlations stay, the
        covariance only widens), with the noise taken about `about` rather than the origin: a
        map's error that varies from place to place is a local shift and turn there, and a
        turn about the origin would also move the map here by the turn times the distance to
        the origin."""
        what = "offset walk" if key == COLONY else f"frame {key!r} walk"
        q_local = _checked_covariance(noise, what)
        c = np.asarray(about, np.float64).reshape(-1)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            msg = f"{what}: expected a finite point (x, y), found {c}"
            raise LocalisationError(msg)
        _, rows = self._used(key, what)
        # b' = (t + dθ J (t - c) + dt, yaw + dθ) for a turn dθ about c and a shift dt: a turn
        # about c seen from the frame's own translation t
        q: np.ndarray = frame_error.about(q_local, c - self._mean[rows][:2])
        q = 0.5 * (q + q.T)
        self._cov[rows, rows] += q
        return q

    def update_frame(
        self,
        key: Hashable,
        pose: np.ndarray,
        covariance: np.ndarray,
        gate: float | None = GATE_3DOF,
    ) -> bool:
        """Fuse a pose (x, y, yaw) measured through frame `key` (`reset_frame` first: a match
        against a map that frame's alignment placed, or a fix put into this agent's frame by
        it) with its own `covariance` alone: the measurement is the true pose moved by the
        frame's error, so it corrects pose and error together. False (and no change) when
        gated out."""
        what = "offset update" if key == COLONY else f"frame {key!r} update"
        z, r = checked_pose(pose, covariance, what)
        _, rows = self._used(key, what)
        x = self.kf.x.ravel()
        b = self._mean[rows]
        c, s = math.cos(b[2]), math.sin(b[2])
        rot = np.array([[c, -s], [s, c]])
        moved = rot @ x[:2]
        h = np.array([moved[0] + b[0], moved[1] + b[1], x[2] + b[2]])
        h_x = np.eye(3)
        h_x[:2, :2] = rot
        h_b = np.zeros((3, len(self._mean)))
        h_b[:, rows] = np.eye(3)
        h_b[:2, rows.start + 2] = (-moved[1], moved[0])
        y = z - h
        y[2] = se2.wrap(float(y[2]))
        return self._fuse(h_x, h_b, y, r, gate)

    def reset_offset(self, covariance: np.ndarray) -> None:
        """Start estimating a new shared map's error (`reset_frame` of `COLONY`)."""
        self.reset_frame(COLONY, covariance)

    def widen_offset(self, covariance: np.ndarray) -> np.ndarray:
        """The shared map's error grew (`widen_frame` of `COLONY`)."""
        return self.widen_frame(COLONY, covariance)

    def walk_offset(self, noise: np.ndarray, about: np.ndarray) -> np.ndarray:
        """Let the shared map's error wander (`walk_frame` of `COLONY`)."""
        return self.walk_frame(COLONY, noise, about)

    def update_offset(
        self, pose: np.ndarray, covariance: np.ndarray, gate: float | None = GATE_3DOF
    ) -> bool:
        """Fuse a pose matched against the shared map (`update_frame` of `COLONY`)."""
        return self.update_frame(COLONY, pose, covariance, gate)


#: Relative asymmetry and negative eigenvalue (of the largest variance) a covariance may have:
#: rounding, not a wrong matrix.
COVARIANCE_TOLERANCE = 1e-6


def _checked_covariance(covariance: np.ndarray, what: str) -> np.ndarray:
    """A 3x3 covariance (symmetrised), or an error saying what was wrong: finite, symmetric and
    positive semi-definite within `COVARIANCE_TOLERANCE` of its largest variance."""
    c = np.asarray(covariance, np.float64)
    if c.shape != (3, 3):
        msg = f"{what}: expected a finite 3x3 covariance, found shape {c.shape}"
        raise LocalisationError(msg)
    if not np.all(np.isfinite(c)):
        msg = f"{what}: expected a finite 3x3 covariance, found non-finite values {c.tolist()}"
        raise LocalisationError(msg)
    found = frame_error.problem(c, COVARIANCE_TOLERANCE)
    if found is not None:
        msg = f"{what}: {found}"
        raise LocalisationError(msg)
    return 0.5 * (c + c.T)


def checked_pose(
    pose: np.ndarray, covariance: np.ndarray, what: str = "pose measurement"
) -> tuple[np.ndarray, np.ndarray]:
    """A pose (3,) and its covariance (3, 3), both finite, or an error naming `what` and saying
    what was wrong."""
    z = np.asarray(pose, np.float64).reshape(-1)
    r = np.asarray(covariance, np.float64)
    if (
        z.shape != (3,)
        or r.shape != (3, 3)
        or not (np.all(np.isfinite(z)) and np.all(np.isfinite(r)))
    ):
        msg = (
            f"{what}: expected a finite pose (x, y, yaw) and a finite 3x3 covariance, found "
            f"{z} and shape {r.shape}"
        )
        raise LocalisationError(msg)
    return z, r


def _seen_from(
    placed: np.ndarray, error: np.ndarray, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where `pose` (3,) appears in keyframes' maps: a keyframe placed at `placed` (G, 3) while
    it truly was at `placed + error` (G, 3) has a map that is the world moved by the rotation
    -error[2] about the placed position and the translation -error[:2]. The poses seen (G, 3),
    their Jacobians by the pose and by the error (G, 3, 3 each)."""
    c, s = np.cos(error[:, 2]), np.sin(error[:, 2])
    back = np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)  # R(-error yaw)
    v = pose[:2] - placed[:, :2] - error[:, :2]
    xy = placed[:, :2] + np.einsum("gij,gj->gi", back, v)
    yaw = (pose[2] - error[:, 2] + math.pi) % (2 * math.pi) - math.pi
    seen = np.column_stack([xy, yaw])
    n = len(placed)
    d_pose = np.tile(np.eye(3), (n, 1, 1))
    d_pose[:, :2, :2] = back
    d_key = np.tile(-np.eye(3), (n, 1, 1))
    d_key[:, :2, :2] = -back
    d_key[:, :2, 2] = np.einsum("gij,gj->gi", back, np.column_stack([v[:, 1], -v[:, 0]]))
    return seen, d_pose, d_key


def _checked_landmark(
    seen: np.ndarray, seen_covariance: np.ndarray, landmark: np.ndarray, covariance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A landmark sighting's (x, y) and 2x2 covariance and the landmark's (symmetrised), or an
    error saying what was wrong: finite, and covariances positive semi-definite."""
    z = np.asarray(seen, np.float64).reshape(-1)
    r_seen = np.asarray(seen_covariance, np.float64)
    lm = np.asarray(landmark, np.float64).reshape(-1)
    r_lm = np.asarray(covariance, np.float64)
    if (
        z.shape != (2,)
        or lm.shape != (2,)
        or r_seen.shape != (2, 2)
        or r_lm.shape != (2, 2)
        or not all(np.all(np.isfinite(a)) for a in (z, lm, r_seen, r_lm))
    ):
        msg = (
            "landmark: expected finite (x, y) positions and 2x2 covariances, found shapes "
            f"{z.shape}, {r_seen.shape}, {lm.shape}, {r_lm.shape}"
        )
        raise LocalisationError(msg)
    for name, c in (("sighting", r_seen), ("landmark", r_lm)):
        found = frame_error.problem(c, COVARIANCE_TOLERANCE)
        if found is not None:
            msg = f"landmark: the {name}'s covariance: {found}"
            raise LocalisationError(msg)
    return z, 0.5 * (r_seen + r_seen.T), lm, 0.5 * (r_lm + r_lm.T)


def _landmark_jacobian(rt: np.ndarray, d: np.ndarray, c: float, s: float) -> np.ndarray:
    """Jacobian (2, 3) by the pose of R(yaw)^T d, d = a point minus the position, R(yaw)^T =
    `rt` = [[c, s], [-s, c]]."""
    jac = np.zeros((2, 3))
    jac[:, :2] = -rt
    jac[:, 2] = np.array([[-s, c], [-c, -s]]) @ d
    return jac
