"""Extended Kalman filter over a planar pose (x, y, yaw) with filterpy: odometry predicts, pose
measurements update."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from voxel.errors import LocalisationError
from voxel.localisation import se2

#: Chi-square 99.9 % quantile with 3 degrees of freedom: a pose measurement farther than this
#: (Mahalanobis distance squared) from the prediction is rejected as an outlier.
GATE_3DOF = 16.27
#: The same with 2 degrees of freedom: a landmark's position seen in the body frame.
GATE_2DOF = 13.82


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


def _jacobian_h(x: np.ndarray) -> np.ndarray:
    return np.eye(3)


def _hx(x: np.ndarray) -> np.ndarray:
    return x


def _residual(z: np.ndarray, hx: np.ndarray) -> np.ndarray:
    y: np.ndarray = z - hx
    y[2] = se2.wrap(float(y[2, 0]))
    return y


@functools.cache
def _filter_class() -> Any:
    """filterpy's EKF with the nonlinear planar motion model as its state prediction.

    Imported on first use: filterpy pulls in scipy.stats (~0.5 s of CPU), which a daemon does
    not need before its first observation."""
    from filterpy.kalman import ExtendedKalmanFilter

    class _Filter(ExtendedKalmanFilter):  # type: ignore[misc]  # filterpy has no type hints
        x: np.ndarray  # the state (3, 1), as filterpy keeps it

        def predict_x(self, u: np.ndarray) -> None:
            self.x = se2.compose(self.x.ravel(), u).reshape(3, 1)

    return _Filter


@dataclass
class Offset:
    """The error of a map the pose is measured against (a colony map: a peer's surfaces put into
    this agent's frame by an alignment), estimated with the pose: a small motion (x, y, yaw)
    about the agent's origin, its covariance and its cross-covariance with the pose."""

    value: np.ndarray  # (3,)
    covariance: np.ndarray  # (3, 3)
    cross: np.ndarray  # (3, 3): cov(pose, offset)


class PlanarEkf:
    """Pose (x, y, yaw) and covariance of one ground agent.

    Optionally also the error of one shared map (`Offset`, `reset_offset`): every match against
    that map shares the alignment's error, so fusing them as independent measurements would
    count the alignment once per scan and carry the robot into the alignment's error. Estimated
    as part of the state, the alignment's error is counted once: however many scans match a
    poor alignment, it moves the pose no more than its covariance against the pose's allows.
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
        self.offset: Offset | None = None

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

    def predict(self, increment: np.ndarray | None) -> None:
        """Move by an odometry increment (dx, dy, dyaw) in the body frame; None: no odometry (stand
        still, widen)."""
        m = self.motion
        if increment is None:
            u = np.zeros(3)
            q_u = np.diag([m.no_odometry**2] * 3)
        else:
            u = np.asarray(increment, np.float64)
            if u.shape != (3,) or not np.all(np.isfinite(u)):
                msg = f"odometry increment: expected 3 finite numbers (dx, dy, dyaw), found {u}"
                raise LocalisationError(msg)
            d = math.hypot(u[0], u[1])
            var_t = m.trans**2 * d + m.still
            q_u = np.diag([var_t, var_t, m.rot**2 * abs(u[2]) + m.rot_per_m**2 * d + m.still])
        yaw = float(self.kf.x[2, 0])
        c, s = math.cos(yaw), math.sin(yaw)
        self.kf.F = np.array(
            [[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0.0, 0.0, 1.0]]
        )
        g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self.kf.Q = g @ q_u @ g.T
        self.kf.predict(u)
        if self.offset is not None:
            self.offset.cross = self.kf.F @ self.offset.cross

    def innovation(self, pose: np.ndarray, covariance: np.ndarray) -> float:
        """Squared Mahalanobis distance of a pose measurement from the prediction."""
        y = _residual(np.asarray(pose, np.float64).reshape(3, 1), self.kf.x.copy())
        s = self.kf.P + covariance
        return float((y.T @ np.linalg.solve(s, y))[0, 0])

    def update(
        self, pose: np.ndarray, covariance: np.ndarray, gate: float | None = GATE_3DOF
    ) -> bool:
        """Fuse a measured pose (x, y, yaw) with its covariance; False (and no change) when gated
        out."""
        z = np.asarray(pose, np.float64).reshape(3, 1)
        r = np.asarray(covariance, np.float64)
        if (
            z.shape != (3, 1)
            or r.shape != (3, 3)
            or not (np.all(np.isfinite(z)) and np.all(np.isfinite(r)))
        ):
            msg = (
                "pose measurement: expected (x, y, yaw) and a finite 3x3 covariance, found "
                f"{z.ravel()} and shape {r.shape}"
            )
            raise LocalisationError(msg)
        if gate is not None and self.innovation(z, r) > gate:
            self.rejected += 1
            return False
        self.kf.update(z, _jacobian_h, _hx, R=r, residual=_residual)
        self.kf.x[2, 0] = se2.wrap(float(self.kf.x[2, 0]))
        off = self.offset
        if off is not None:  # the offset learns from the pose through their correlation
            gain = off.cross.T @ self.kf.SI  # (3, 3)
            off.value = off.value + (gain @ self.kf.y).ravel()
            off.value[2] = se2.wrap(float(off.value[2]))
            off.covariance = off.covariance - gain @ off.cross
            off.covariance = 0.5 * (off.covariance + off.covariance.T)
            off.cross = off.cross - self.kf.K @ off.cross
        self.accepted += 1
        return True

    def update_landmark(
        self,
        seen: np.ndarray,
        seen_covariance: np.ndarray,
        landmark: np.ndarray,
        landmark_covariance: np.ndarray,
        gate: float | None = GATE_2DOF,
    ) -> bool:
        """Fuse a landmark (paper Alg. 3): an object whose position (x, y) `landmark` in this
        agent's frame is known with `landmark_covariance` (2x2), seen at `seen` (x, y) in the
        body frame with `seen_covariance` (2x2). The measurement is R(yaw)^T (landmark -
        position); its covariance adds both. False (and no change) when gated out."""
        z = np.asarray(seen, np.float64).reshape(-1)
        r_seen = np.asarray(seen_covariance, np.float64)
        lm = np.asarray(landmark, np.float64).reshape(-1)
        r_lm = np.asarray(landmark_covariance, np.float64)
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
        x = self.kf.x.ravel()
        c, s = math.cos(x[2]), math.sin(x[2])
        rt = np.array([[c, s], [-s, c]])  # world -> body
        d = lm - x[:2]
        y = z - rt @ d
        jac = np.zeros((2, 3))
        jac[:, :2] = -rt
        jac[:, 2] = np.array([[-s, c], [-c, -s]]) @ d
        noise = r_seen + rt @ r_lm @ rt.T
        return self._fuse(jac, y, noise, gate)

    def _fuse(self, jac: np.ndarray, y: np.ndarray, noise: np.ndarray, gate: float | None) -> bool:
        """A measurement of the pose alone (Jacobian `jac` (k, 3), innovation `y` (k,), noise
        (k, k)): gated, fused (Joseph form), the offset's estimate kept consistent."""
        p = self.kf.P
        innov = jac @ p @ jac.T + noise
        if gate is not None and float(y @ np.linalg.solve(innov, y)) > gate:
            self.rejected += 1
            return False
        si = np.linalg.inv(innov)
        gain = p @ jac.T @ si
        x = self.kf.x.ravel() + gain @ y
        x[2] = se2.wrap(float(x[2]))
        i_kh = np.eye(3) - gain @ jac
        off = self.offset
        if off is not None:
            hx = jac @ off.cross  # (k, 3)
            off.value = off.value + hx.T @ si @ y
            off.value[2] = se2.wrap(float(off.value[2]))
            off.covariance = off.covariance - hx.T @ si @ hx
            off.covariance = 0.5 * (off.covariance + off.covariance.T)
            off.cross = i_kh @ off.cross
        self.kf.x = x.reshape(3, 1)
        new_p = i_kh @ p @ i_kh.T + gain @ noise @ gain.T
        self.kf.P = 0.5 * (new_p + new_p.T)
        self.accepted += 1
        return True

    def reset_offset(self, covariance: np.ndarray) -> None:
        """Start estimating a new shared map's error: zero, with `covariance` (x, y, yaw about
        the origin: the alignment's), uncorrelated with the pose."""
        c = np.asarray(covariance, np.float64)
        if c.shape != (3, 3) or not np.all(np.isfinite(c)):
            msg = f"offset: expected a finite 3x3 covariance, found shape {c.shape}"
            raise LocalisationError(msg)
        self.offset = Offset(np.zeros(3), c.copy(), np.zeros((3, 3)))

    def update_offset(
        self, pose: np.ndarray, covariance: np.ndarray, gate: float | None = GATE_3DOF
    ) -> bool:
        """Fuse a pose (x, y, yaw) measured against the shared map whose error `offset` holds
        (`reset_offset` first): the measurement is the true pose moved by that error, so it
        corrects pose and error together. False (and no change) when gated out."""
        off = self.offset
        if off is None:
            msg = "offset update: expected reset_offset() before the first update"
            raise LocalisationError(msg)
        z = np.asarray(pose, np.float64).reshape(3)
        r = np.asarray(covariance, np.float64)
        if r.shape != (3, 3) or not (np.all(np.isfinite(z)) and np.all(np.isfinite(r))):
            msg = (
                "pose measurement: expected (x, y, yaw) and a finite 3x3 covariance, found "
                f"{z} and shape {r.shape}"
            )
            raise LocalisationError(msg)
        x = self.kf.x.ravel()
        b = off.value
        c, s = math.cos(b[2]), math.sin(b[2])
        rot = np.array([[c, -s], [s, c]])
        moved = rot @ x[:2]
        h = np.array([moved[0] + b[0], moved[1] + b[1], x[2] + b[2]])
        h_x = np.eye(3)
        h_x[:2, :2] = rot
        h_b = np.eye(3)
        h_b[:2, 2] = (-moved[1], moved[0])
        jac = np.hstack([h_x, h_b])  # (3, 6)
        p6 = np.block([[self.kf.P, off.cross], [off.cross.T, off.covariance]])
        y = z - h
        y[2] = se2.wrap(float(y[2]))
        innov = jac @ p6 @ jac.T + r
        if gate is not None and float(y @ np.linalg.solve(innov, y)) > gate:
            self.rejected += 1
            return False
        gain = p6 @ jac.T @ np.linalg.inv(innov)  # (6, 3)
        state = np.concatenate([x, b]) + gain @ y
        i_kh = np.eye(6) - gain @ jac
        p6 = i_kh @ p6 @ i_kh.T + gain @ r @ gain.T
        p6 = 0.5 * (p6 + p6.T)
        state[2], state[5] = se2.wrap(float(state[2])), se2.wrap(float(state[5]))
        self.kf.x = state[:3].reshape(3, 1)
        self.kf.P = p6[:3, :3].copy()
        self.offset = Offset(state[3:].copy(), p6[3:, 3:].copy(), p6[:3, 3:].copy())
        self.accepted += 1
        return True
