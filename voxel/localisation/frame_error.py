"""Frame error: the uncertainty of a planar transform between two agents' frames, as a small
rigid motion (x, y, yaw) applied after it, moved between frames and to where it is used."""

from __future__ import annotations

import math

import numpy as np

from voxel.errors import LocalisationError

#: Indices of x, y and yaw in a 6x6 covariance ordered x y z roll pitch yaw.
PLANAR = [0, 1, 5]

#: Floor of an alignment's standard deviations (m, m, rad): no map alignment is trusted to
#: better than a centimetre and a tenth of a degree, whatever its residuals.
FLOOR = np.diag([0.01**2, 0.01**2, math.radians(0.1) ** 2])


def _check(cov: np.ndarray) -> np.ndarray:
    c = np.asarray(cov, np.float64)
    if c.shape != (3, 3) or not np.all(np.isfinite(c)):
        msg = f"frame error: expected a finite 3x3 covariance (x, y, yaw), found shape {c.shape}"
        raise LocalisationError(msg)
    return c


def about(cov: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """A covariance (x, y, yaw) of a motion rotating about `centre` (x, y) re-expressed as one
    rotating about the frame's origin: a yaw error about a point 5 m away moves the origin too."""
    c = np.asarray(centre, np.float64).reshape(-1)[:2]
    a = np.array([[1.0, 0.0, c[1]], [0.0, 1.0, -c[0]], [0.0, 0.0, 1.0]])
    out: np.ndarray = a @ _check(cov) @ a.T
    return out


def at(cov: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The covariance (x, y, yaw) that a frame error `cov` (about the origin) gives a pose at
    `xy`: a yaw error moves a pose far from the origin by its distance times the angle."""
    p = np.asarray(xy, np.float64).reshape(-1)[:2]
    j = np.array([[1.0, 0.0, -p[1]], [0.0, 1.0, p[0]], [0.0, 0.0, 1.0]])
    out: np.ndarray = j @ _check(cov) @ j.T
    return out


def adjoint(transform: np.ndarray) -> np.ndarray:
    """3x3 matrix taking a small motion (x, y, yaw) applied in frame B into the same motion
    applied in frame A, for the 4x4 `transform` taking B's points into A's (planar part)."""
    t = np.asarray(transform, np.float64)
    c, s = t[0, 0], t[1, 0]
    norm = math.hypot(c, s) or 1.0
    c, s = c / norm, s / norm
    return np.array([[c, -s, t[1, 3]], [s, c, -t[0, 3]], [0.0, 0.0, 1.0]])


def moved(cov: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """A frame error expressed in frame B moved into frame A (`transform` takes B into A)."""
    ad = adjoint(transform)
    out: np.ndarray = ad @ _check(cov) @ ad.T
    return out


def planar(cov6: np.ndarray) -> np.ndarray:
    """x, y, yaw block of a 6x6 covariance ordered x y z roll pitch yaw."""
    c = np.asarray(cov6, np.float64).reshape(6, 6)
    out: np.ndarray = c[np.ix_(PLANAR, PLANAR)].copy()
    return out


def floored(cov: np.ndarray) -> np.ndarray:
    """`cov` with its variances raised to at least `FLOOR`'s (a peer's offer may claim less)."""
    c = _check(cov)
    out: np.ndarray = c + np.diag(np.maximum(np.diag(FLOOR) - np.diag(c), 0.0))
    return out


def problem(c: np.ndarray, tolerance: float) -> str | None:
    """What keeps the square matrix `c` from being a covariance, or None: symmetric and positive
    semi-definite within `tolerance` times its largest variance (rounding, not a wrong matrix)."""
    tol = tolerance * max(float(np.abs(np.diag(c)).max()), 1e-12)
    asym = float(np.abs(c - c.T).max())
    if asym > tol:
        return f"expected a symmetric covariance, found entries {asym:.3g} apart"
    low = float(np.linalg.eigvalsh(0.5 * (c + c.T)).min())
    if low < -tol:
        return f"expected a positive semi-definite covariance, found an eigenvalue {low:.3g}"
    return None


def positive(cov: np.ndarray) -> np.ndarray:
    """`cov` made a covariance: symmetrised, its negative eigenvalues raised to zero (the nearest
    positive semi-definite matrix). A peer's covariance is checked positive semi-definite only
    to a tolerance of its largest variance (its z may dwarf its x, y, yaw), and a filter fed a
    negative variance trusts a measurement more than certainty."""
    c = _check(cov)
    out: np.ndarray = 0.5 * (c + c.T)
    values, vectors = np.linalg.eigh(out)
    if values[0] < 0.0:
        out = (vectors * np.maximum(values, 0.0)) @ vectors.T
        out = 0.5 * (out + out.T)
    return out


def difference(t1: np.ndarray, t2: np.ndarray) -> np.ndarray:
    """The small motion (x, y, yaw), applied after `t1`, that gives `t2` (both 4x4, same frames)."""
    d = np.asarray(t2, np.float64) @ np.linalg.inv(np.asarray(t1, np.float64))
    return np.array([d[0, 3], d[1, 3], math.atan2(d[1, 0], d[0, 0])])


def from_residuals(
    cov: np.ndarray, rmse: float, centre: np.ndarray, scatter: np.ndarray | None = None
) -> np.ndarray:
    """An honest covariance (x, y, yaw, about the frame's origin) of a map alignment.

    `cov` is the fit's least-squares covariance about `centre` (residual variance times the
    inverse normal matrix): its shape says which directions the geometry constrains (a
    corridor's axis, the yaw lever of the overlap), but its size shrinks with the number of
    points as if their residuals were independent. They are not: two maps disagree where their
    agents' own poses drifted, a systematic error shared by every point of a wall. So its size
    is set so that the best constrained direction has the fit's RMS residual `rmse` as its
    standard deviation, then `scatter` (the disagreement of successive estimates of the same
    alignment, a vector or a covariance) is added, and `FLOOR` bounds it below.
    """
    c = _check(cov)
    if not math.isfinite(rmse) or rmse < 0:
        msg = f"frame error: expected a finite residual >= 0, found {rmse}"
        raise LocalisationError(msg)
    c = 0.5 * (c + c.T)
    var_t = float(np.min(np.linalg.eigvalsh(c[:2, :2])))
    scaled = c * (rmse**2 / var_t) if var_t > 0 else np.diag([1e6, 1e6, 1e6])
    out = about(scaled, centre)
    if scatter is not None:
        s = np.asarray(scatter, np.float64)
        out = out + (np.outer(s, s) if s.shape == (3,) else _check(s))
    result: np.ndarray = out + FLOOR
    return result
