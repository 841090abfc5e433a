"""Pose fixes: the error a fixed camera claims for a robot it saw, and the fix in its frame."""

from __future__ import annotations

import math

import numpy as np

from colonyd.alignment import ColonyFrame
from voxel.localisation import frame_error, se2
from voxel.localisation.localiser import Through

#: The fix models: "flat" (`FLAT_XY_M`, `YAW_SD`) and "fitted" (`FIX_ALONG_M`, `FIX_ACROSS_M`,
#: `FIX_YAW_RAD`); `FIX_MODEL` is the daemon's. The fitted model is honest over range but failed
#: its A/B rule (docs/BENCHMARKS.md "The CCTV's claimed covariances"): the NEES of the
#: experiment's fixes (one board seen edge-on: range alone cannot tell it) and the offline ATE
#: (seed 1: office depth-1 0.041 -> 0.191 m, hall lidar-1 0.047 -> 0.071; the alignment the fixes
#: go through claims less than its error): the daemon keeps "flat" (5-17x the error below 7.5 m).
#: "angle" (the fitted model grown with the board's incidence, `FIX_ANGLE_K`) halves the
#: calibration's edge-on NEES but failed its A/B rule as the fitted one did (5 of 10
#: world-seeds; seed 1: office depth-1 0.041 -> 0.452 m, hall lidar-1 0.047 -> 0.077;
#: docs/BENCHMARKS.md "The fix's claim by the board's angle"): a bench model; the daemon's
#: `_send_fixes` passes no incidence.
FIX_MODELS = ("flat", "fitted", "angle")
FIX_MODEL = "flat"
#: The flat model: (floor, per metre of range) of the x and y standard deviation (m), and the yaw
#: one (rad) at any range. Set before the CCTV's corners were refined; now 3-5x the errors.
FLAT_XY_M = (0.01, 0.01)
YAW_SD = math.radians(4.0)
#: The fitted model: a fix's standard deviations as `floor + per * range**RANGE_POWER` (range in m,
#: the camera to the robot's body at the floor): (floor, per) along the horizontal ray from the
#: camera (m), across it (m), and in yaw (rad). Fitted by maximum likelihood (a Gaussian error,
#: powers 1-4 tried, 4 the likeliest on every axis; rounded) to the errors of 199 boards the sim's
#: cctv-1 (640 x 480, 75 degrees, 2.5 m up; 0.24 m boards 0.7 m up) sent as fixes from 700 images
#: of one robot each (300 in the office, 400 in the hall), anywhere on lidar-1's or depth-1's path,
#: any heading, at 3.3-12.5 m (`python -m colonyd.bench.fix_calibration`, docs/BENCHMARKS.md "The
#: CCTV's claimed covariances"): along, RMS 0.3-0.5 cm to 5 m, 1.6 at 7, 4.6 at 8.5-12.5 (the
#: board's known height fixes its range along the ray's slope: a pixel of its centre is r^2 / (1.8
#: m x f), and the centre's error grows as the board shrinks); across 0.5-0.8 cm, 1.5 beyond 7 m;
#: yaw 0.3-0.8 degrees to 7 m, 2.2 at 7-8.5, 4.0 beyond. Each per-image error: the sampled images
#: are independent and the errors' mean per range bin is under a fifth of their RMS up to 9 m (at
#: 9-10.5 m, 7 fixes: +4 cm along of 6 RMS, -3.6 degrees of 6.5).
FIX_ALONG_M = (0.0031, 4.97e-6)
FIX_ACROSS_M = (0.0052, 1.48e-6)
FIX_YAW_RAD = (0.0035, 6.87e-6)
RANGE_POWER = 4
#: The "angle" model: the fitted model's standard deviations, each times 1 + k tan^2(incidence),
#: the incidence the angle between the board's solved normal and the camera's ray to it (0 square
#: on; `CctvCamera.board_incidence`), capped at `MAX_INCIDENCE`: k along the ray, across it, in
#: yaw. Fitted by maximum likelihood (a Gaussian error, the fitted model's sd over range kept;
#: tan^2 likelier than 1 / cos - 1 and tan) to the same 198 boards (`python -m
#: colonyd.bench.fix_calibration`, docs/BENCHMARKS.md "The fix's claim by the board's angle"):
#: along and across grow edge-on (x1.6 and x1.9 at 75 degrees, x2.3 and x3.0 at 80), the yaw
#: does not (k 0).
FIX_ANGLE_K = (0.040, 0.064, 0.0)
MAX_INCIDENCE = math.radians(85.0)
#: An alternative measured offline (`cctv_offline --fix-model new`, not the daemon's): a yaw
#: standard deviation per metre of range, as a board's solved normal gets worse the smaller it
#: looks (sim office, cctv-1, 0.24 m boards, before the corners' refinement: RMS 2 degrees at
#: 4.7-5.6 m, 5-7 at 6.5-8 m, up to 11; docs/BENCHMARKS.md "The CCTV's fixes offline").
YAW_PER_M = math.radians(1.0)


def fix_sd(model: tuple[float, float], range_m: float) -> float:
    """A fix's standard deviation on one axis (`FIX_ALONG_M`, `FIX_ACROSS_M`, `FIX_YAW_RAD`) at
    `range_m` m."""
    floor, per = model
    return floor + per * range_m**RANGE_POWER


def fix_covariance(
    range_m: float,
    yaw_per_m: float | None = None,
    ray: np.ndarray | None = None,
    model: str = FIX_MODEL,
    incidence: float | None = None,
) -> np.ndarray:
    """The covariance (6x6, x y z roll pitch yaw, the camera's site frame) a CCTV sends with a
    robot's body pose seen `range_m` m away, by `model` (`FIX_MODELS`): "flat", `FLAT_XY_M` in x
    and y and `YAW_SD` in yaw; "fitted", `FIX_ALONG_M` along `ray` (the horizontal direction
    from the camera to the robot, x and y, any length) and `FIX_ACROSS_M` across it, or the
    along one in every direction without a ray or with a zero one (the larger: claims no less
    than the error), and `FIX_YAW_RAD` in yaw; "angle", the fitted model's each times 1 + k
    tan^2(`incidence`) (`FIX_ANGLE_K`; `incidence` in radians, 0 to pi/2, needed by this model
    only: the board's normal against the camera's ray). `yaw_per_m`: yaw `yaw_per_m` per metre
    of range instead (`cctv_offline`'s alternative). 5 cm and 0.05 rad in z, roll and pitch (a
    planar robot's fix carries none)."""
    if not (math.isfinite(range_m) and range_m >= 0.0):
        msg = f"range_m: expected a finite range >= 0 in metres, found {range_m!r}"
        raise ValueError(msg)
    if model not in FIX_MODELS:
        msg = f"model: expected one of {FIX_MODELS}, found {model!r}"
        raise ValueError(msg)
    if model == "flat":
        along = across = FLAT_XY_M[0] + FLAT_XY_M[1] * range_m
        yaw = YAW_SD
    else:
        along = fix_sd(FIX_ALONG_M, range_m)
        across = fix_sd(FIX_ACROSS_M, range_m)
        yaw = fix_sd(FIX_YAW_RAD, range_m)
    if model == "angle":
        if incidence is None or not (math.isfinite(incidence) and 0.0 <= incidence <= math.pi / 2):
            msg = (
                f"incidence: expected the board's angle to the ray, 0 to pi/2, found {incidence!r}"
            )
            raise ValueError(msg)
        grow = math.tan(min(incidence, MAX_INCIDENCE)) ** 2
        along, across, yaw = (
            sd * (1.0 + k * grow) for sd, k in zip((along, across, yaw), FIX_ANGLE_K, strict=True)
        )
    if yaw_per_m is not None:
        yaw = yaw_per_m * range_m
    cov = np.diag([along**2, along**2, 0.05**2, 0.05**2, 0.05**2, yaw**2])
    if ray is not None:
        d = np.asarray(ray, np.float64).reshape(-1)[:2]
        n = float(np.linalg.norm(d))
        if not np.isfinite(d).all():
            msg = f"ray: expected a finite horizontal direction (x, y), found {ray!r}"
            raise ValueError(msg)
        if n > 1e-9:  # a robot right below the camera: no direction, the along sd everywhere
            u = d / n
            cov[:2, :2] = across**2 * np.eye(2) + (along**2 - across**2) * np.outer(u, u)
    return cov


def sightings_covariance(
    rmse: float,
    spread: float,
    positions: np.ndarray,
    drift: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Error of a frame fitted to sightings (6x6, x y z roll pitch yaw, about our origin): the
    fit's residual in x and y, about the sightings' centroid, and a yaw of that residual over
    their spread (a lever of `spread` metres); with `drift`, plus our own pose's error when we
    were seen (our estimate (x, y, yaw) at the newest sighting and a 3x3 covariance of it, a
    motion about that position: `cctv_offline` gives the filter's when the sighting arrives,
    no less than at its stamp, as it only grows between fixes).

    The residual shows only how well the sightings fit one transform. Our estimates they are
    paired with carry our drift since our origin, nearly the same in every sighting of a short
    while, so the fit takes it into the transform without a trace in the residual: an
    alignment from sightings is wrong by our own error then (sim: 0.19-0.38 degrees off while
    its residual claimed 0.11-0.13, docs/BENCHMARKS.md "The CCTV's claimed covariances"). The
    daemon does not pass `drift`: honest, it made the fixes weigh less and lost their help
    (docs/BENCHMARKS.md "An alignment from sightings counting the robot's drift");
    `cctv_offline --sightings drift` measures it."""
    planar = frame_error.about(
        np.diag([rmse**2, rmse**2, (rmse / max(spread, 0.1)) ** 2]),
        positions[:, :2].mean(axis=0),
    )
    if drift is not None:
        pose, covariance = drift
        own = np.asarray(covariance, np.float64)
        planar = planar + frame_error.about(0.5 * (own + own.T), np.asarray(pose)[:2])
    cov = np.zeros((6, 6))
    cov[np.ix_(frame_error.PLANAR, frame_error.PLANAR)] = frame_error.floored(planar)
    return cov


def fix_in_own_frame(
    frame: ColonyFrame,
    own: str,
    origin: str,
    body: np.ndarray,
    covariance: np.ndarray,
    count: int = 1,
    bias: float = 0.0,
    alignment: bool = True,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A fix from `origin` (the robot's body pose `body`, 4x4 in origin's frame, with its 6x6
    `covariance`) in `own`'s frame through the colony frame: the body pose (x, y, yaw) and its
    covariance (3x3: the fix's, rotated, plus `count` times the alignments' error at the robot's
    position, `frame_error.at`). None when either frame is not aligned.

    Every fix through one alignment shares its error, and the daemon counts it in each (count 1).
    Measured alternatives (`cctv_offline --fix-model new|shared`, `FixCounter`): the k-th fix
    through one alignment carrying `count` = k times that error (n fixes tell the filter about
    it H_n = 1 + 1/2 + ... + 1/n times what one does, 3.4 for 17, not n times), or k(k+1)
    times (at most once in all); `bias` (m): a systematic error of the camera's positions,
    shared by its fixes like the alignment's error and counted with it. Without `alignment`,
    the fix's own covariance alone (rotated; no alignment's error, no `bias`): for a filter that
    estimates the alignment's error as a state (`through`, `ScanParams.alignment_frames`)."""
    mine, theirs = frame.transforms.get(own), frame.transforms.get(origin)
    if mine is None or theirs is None:
        return None
    to_own = np.linalg.inv(mine) @ theirs
    seen = to_own @ np.asarray(body, np.float64)
    # a peer's covariance is checked to a tolerance of its largest variance: made positive
    cov = frame_error.positive(frame_error.planar(np.asarray(covariance, np.float64)))
    rot = np.eye(3)
    rot[:2, :2] = to_own[:2, :2]
    if not alignment:
        return se2.from_matrix(seen), rot @ cov @ rot.T
    error = frame_error.moved(frame.covariance(own) + frame.covariance(origin), np.linalg.inv(mine))
    shared = frame_error.at(error, seen[:2, 3]) + np.diag([bias**2, bias**2, 0.0])
    out = rot @ cov @ rot.T + max(1, count) * shared
    return se2.from_matrix(seen), out


def through(frame: ColonyFrame, own: str, origin: str) -> Through | None:
    """The alignment of `origin`'s frame into `own`'s through the colony frame, for a filter
    that estimates its error (`ScanLocaliser.fix` and `landmark`): its transform, rounded to
    1e-4 (as `FixCounter.key`: a changed alignment is a new error), and its error's covariance
    (x, y, yaw about `own`'s origin: both frames' errors in the colony frame, moved into ours).
    None when either frame is not aligned."""
    mine, theirs = frame.transforms.get(own), frame.transforms.get(origin)
    if mine is None or theirs is None:
        return None
    back = np.linalg.inv(mine)
    key = bytes(np.round(back @ theirs, 4).tobytes())
    error = frame_error.moved(frame.covariance(own) + frame.covariance(origin), back)
    return Through(origin, key, frame_error.positive(error))


class FixCounter:
    """Fixes fused so far through each sender's current alignment (its transform into ours,
    rounded): the next one's `count` for `fix_in_own_frame` (`cctv_offline --fix-model new`).
    A changed alignment starts again."""

    def __init__(self) -> None:
        self._counts: dict[str, tuple[bytes, int]] = {}

    def key(self, frame: ColonyFrame, own: str, origin: str) -> bytes | None:
        """What the fixes from `origin` go through: the transform of its frame into ours."""
        mine, theirs = frame.transforms.get(own), frame.transforms.get(origin)
        if mine is None or theirs is None:
            return None
        return bytes(np.round(np.linalg.inv(mine) @ theirs, 4).tobytes())

    def next(self, origin: str, key: bytes) -> int:
        """The count of the next fix from `origin` through the alignment `key`."""
        kept = self._counts.get(origin)
        return 1 if kept is None or kept[0] != key else kept[1] + 1

    def fused(self, origin: str, key: bytes) -> None:
        """A fix from `origin` through `key` was fused."""
        self._counts[origin] = (key, self.next(origin, key))
