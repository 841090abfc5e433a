"""The marker corners bench: on an area-sampled image the refined corners are on the square,
OpenCV's subpixel corners inside it."""

from __future__ import annotations

from colonyd.bench.marker_corners import main


def test_refined_corners_are_on_the_square_and_subpix_corners_inside(capsys):
    (row,) = main(["--distances", "5", "--yaws", "0.3"])
    assert "area_edges" in capsys.readouterr().out
    assert 25.0 < row["side_px"] < 30.0
    assert abs(row["area_edges_inward_px"]) < 0.02 and abs(row["area_edges_range_pct"]) < 0.2
    assert row["area_subpix_inward_px"] > 0.15 and row["area_subpix_range_pct"] > 1.0
    assert abs(row["sim_edges_inward_px"]) < 0.1 and abs(row["sim_edges_range_pct"]) < 1.0


def test_clutter_beside_a_marker_is_claimed(capsys):
    rows = main(["--clutter", "--distances", "3"])
    assert "fallen back" in capsys.readouterr().out
    assert len(rows) > 20 and any(r["fallback"] for r in rows)
    assert max(r["sigmas"] for r in rows) < 4.0  # 12.6 sd before EDGE_SPREAD_PX
