"""The landmarks' offline harness on a few seconds of the office: depth-1 aligned by the CCTV's
sightings fuses its fixes and the markers the CCTV published as landmarks, here through the
alignment's error as one state of its filter, and appends its result as a JSON line."""

from __future__ import annotations

import json

from colonyd.bench.cctv_landmarks import main


def test_cctv_landmarks_fuses_published_markers_through_the_alignments_frame(tmp_path):
    out = tmp_path / "landmarks.jsonl"
    args = ["--world", "office", "--seed", "1", "--duration", "10", "--modes", "once"]
    got = main([*args, "--alignment", "state", "--json", str(out)])
    assert got["alignment"] == "state" and set(got["published"][0]["markers"]) >= {1, 3}
    run = got["once"]
    assert 0.0 < run["depth_aligned_at"] < 10.0  # by the CCTV's sightings first
    fused, refused = run["depth_landmarks"]
    assert fused > 0 and fused + refused > 0, run["depth_landmarks"]
    assert run["depth_fixes"][0] > 0
    frame = run["depth_alignment"]  # the filter estimated the alignment's error
    assert frame["estimated_yaw_sd_deg"] < frame["claimed_yaw_deg"] * 1.01, frame
    assert 0.0 <= run["depth_ate"] < 0.2
    (line,) = out.read_text().splitlines()
    assert json.loads(line)["once"]["depth_ate"] == run["depth_ate"]
