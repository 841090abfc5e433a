"""The CCTV markers bench: its published markers' errors along the ray are within their claim."""

from __future__ import annotations

import numpy as np

from colonyd.bench.cctv_markers import main


def test_hall_markers_are_published_with_the_error_they_have(capsys):
    rows = main(["--world", "hall", "--frames", "3"])
    assert rows and "claimed along m" in capsys.readouterr().out
    along = np.array([abs(r["along_m"]) for r in rows])
    claimed = np.array([r["claimed_along_m"] for r in rows])
    across = np.array([r["across_m"] for r in rows])
    assert (along <= 2.0 * claimed).all(), (along, claimed)  # honest along the ray (< 2 sd)
    assert across.max() < 0.02  # and good across it
    far = np.array([r["range_m"] for r in rows]) > 8.0
    assert far.any() and (claimed[far] > 0.1).all()  # a far marker does not claim a centimetre
