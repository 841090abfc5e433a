"""The fix calibration bench's fit and error decomposition (known answers, no rendering)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from colonyd.bench.fix_calibration import by_range, fit_angle, fit_sd, fix_row
from colonyd.fixes import FIX_ACROSS_M, FIX_ALONG_M, FIX_YAW_RAD, fix_covariance, fix_sd
from plugins.cctv import CctvCamera
from voxel.localisation import se2


def test_fit_sd_recovers_the_floor_and_slope_errors_were_drawn_with() -> None:
    rng = np.random.default_rng(3)
    r = rng.uniform(3.0, 11.0, 4000)
    e = rng.normal(size=r.size) * (0.003 + 5e-6 * r**4)
    floor, per, _ = fit_sd(r, e, 4)
    assert floor == pytest.approx(0.003, rel=0.15)
    assert per == pytest.approx(5e-6, rel=0.1)


def test_a_fix_error_splits_along_and_across_the_ray_from_the_camera() -> None:
    cam = CctvCamera(fov=1.0)  # at the origin
    truth = np.array([4.0, 0.0, 0.0])
    body = se2.to_matrix(np.array([4.03, -0.01, 0.02]))  # 3 cm long, 1 cm right, 0.02 rad
    cov = fix_covariance(4.0, ray=body[:2, 3], model="fitted")
    row = fix_row(cam, body, cov, truth, 4.0)
    assert row["along_m"] == pytest.approx(0.03, abs=1e-4)
    assert row["across_m"] == pytest.approx(-0.01, abs=1e-3)
    assert row["yaw_rad"] == pytest.approx(0.02)
    assert row["sd_along_m"] == pytest.approx(math.sqrt(cov[0, 0]), rel=1e-3)
    row.update(image=0, robot="r")
    (bin_,) = by_range([row])
    assert bin_["n"] == 1 and bin_["along_mean"] == pytest.approx(3.0, abs=0.01)  # cm


def test_fit_angle_recovers_the_growth_errors_were_drawn_with() -> None:
    rng = np.random.default_rng(5)
    n = 6000
    r = rng.uniform(3.0, 10.0, n)
    angle = rng.uniform(0.0, 80.0, n)
    grow = np.tan(np.radians(angle)) ** 2
    rows = []
    for axis, model, k in (
        ("along_m", FIX_ALONG_M, 0.1),
        ("across_m", FIX_ACROSS_M, 0.03),
        ("yaw_rad", FIX_YAW_RAD, 0.0),
    ):
        sd = np.array([fix_sd(model, x) for x in r]) * (1.0 + k * grow)
        e = rng.normal(size=n) * sd
        for i in range(n):
            if not rows or len(rows) <= i:
                rows.append({"range_m": r[i], "incidence_deg": angle[i]})
            rows[i][axis] = e[i]
    fit = fit_angle(rows)
    assert fit["along_m"] == pytest.approx(0.1, rel=0.15)
    assert fit["across_m"] == pytest.approx(0.03, rel=0.15)
    assert fit["yaw_rad"] < 0.005
