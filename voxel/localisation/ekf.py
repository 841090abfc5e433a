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


class PlanarEkf:
    """Pose (x, y, yaw) and covariance of one ground agent."""

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
        self.accepted += 1
        return True
