"""Tests of the RGB-D folder readers on the real 7-Scenes frames and on a TUM-layout copy."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from plugins.errors import ParseError, SourceError, SourceSpecError
from plugins.sevenscenes import RgbdSource, read_depth_png, read_matrix
from tests.shared import SHARED_DATA
from voxel.rotation import matrix_to_quaternion

DATA = SHARED_DATA
KITCHEN = DATA / "redkitchen-50"
needs_kitchen = pytest.mark.skipif(
    not KITCHEN.is_dir(), reason=f"real 7-Scenes frames not found at {KITCHEN}"
)


@needs_kitchen
def test_real_frames_intrinsics_and_poses() -> None:
    source = RgbdSource(KITCHEN)
    assert source.layout == "7scenes" and len(source) == 50
    np.testing.assert_allclose(source.adapter.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    first = next(iter(source))
    pose = read_matrix(KITCHEN / "frames" / "frame-000150.pose.txt", (4, 4))
    np.testing.assert_allclose(first.pose, pose)
    assert first.time == pytest.approx(150 / 30)
    raw = read_depth_png(KITCHEN / "frames" / "frame-000150.depth.png")
    valid = (raw > 0) & (raw < 65535)
    assert len(first) == int(valid.sum())
    np.testing.assert_allclose(np.sort(first.points[:, 2]), np.sort(raw[valid] / 1000.0), rtol=1e-6)


@needs_kitchen
def test_two_frames_agree_in_the_world_frame() -> None:
    from scipy.spatial import cKDTree

    source = RgbdSource(KITCHEN, step=10, stride=4)
    a, b = list(source)[:2]
    distances, _ = cKDTree(a.points_world()).query(b.points_world())
    assert np.median(distances) < 0.02  # README: about 1 cm with the right poses


@needs_kitchen
def test_truncated_png_and_bad_pose_are_skipped_and_counted(tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in (150, 151, 152):
        for kind in ("depth.png", "pose.txt"):
            shutil.copy(KITCHEN / "frames" / f"frame-000{i}.{kind}", frames)
    png = frames / "frame-000151.depth.png"
    png.write_bytes(png.read_bytes()[:5000])
    (frames / "frame-000152.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 zero\n0 0 0 1\n")
    source = RgbdSource(tmp_path)
    scans = list(source)
    assert len(scans) == 1 and source.stats.skipped == 2
    text = " ".join(source.stats.first_errors)
    assert (
        "frame-000151.depth.png: expected a readable 16-bit PNG, "
        "found an unreadable or truncated file" in text
    )
    assert "frame-000152.pose.txt:3: field 4: expected a number, found 'zero'" in text
    with pytest.raises(
        ParseError, match=r"frame-000151\.depth\.png: expected a readable 16-bit PNG"
    ):
        list(RgbdSource(tmp_path, strict=True))


@needs_kitchen
def test_tum_layout(tmp_path: Path) -> None:
    lines_depth, lines_truth = ["# depth maps"], ["# ground truth"]
    for i in range(150, 155):
        stamp = 1000.0 + (i - 150) / 30
        raw = read_depth_png(KITCHEN / "frames" / f"frame-000{i}.depth.png")
        tum = np.where((raw > 0) & (raw < 65535), raw.astype(np.uint32) * 5, 0).astype(
            np.uint16
        )  # 5000 per metre
        (tmp_path / "depth").mkdir(exist_ok=True)
        import cv2

        cv2.imwrite(str(tmp_path / "depth" / f"{stamp:.6f}.png"), tum)
        lines_depth.append(f"{stamp:.6f} depth/{stamp:.6f}.png")
        pose = read_matrix(KITCHEN / "frames" / f"frame-000{i}.pose.txt", (4, 4))
        q = matrix_to_quaternion(pose[:3, :3] / np.linalg.norm(pose[:3, :3], axis=0))
        t = pose[:3, 3]
        lines_truth.append(f"{stamp + 0.004:.6f} {t[0]} {t[1]} {t[2]} {q[0]} {q[1]} {q[2]} {q[3]}")
    (tmp_path / "depth.txt").write_text("\n".join(lines_depth) + "\n")
    (tmp_path / "groundtruth.txt").write_text("\n".join(lines_truth) + "\n")
    source = RgbdSource(tmp_path)
    assert source.layout == "tum" and len(source) == 5
    obs = next(iter(source))
    np.testing.assert_allclose(
        obs.origin, read_matrix(KITCHEN / "frames" / "frame-000150.pose.txt", (4, 4))[:3, 3]
    )
    assert obs.points[:, 2].max() < 6.0  # millimetres * 5 read back as metres
    (tmp_path / "groundtruth.txt").write_text("1000.0 1 2 3\n")
    with pytest.raises(
        ParseError,
        match=(
            r"groundtruth\.txt: at time 1000\.0: expected 'timestamp tx ty tz qx qy qz qw', "
            r"found 4 fields"
        ),
    ):
        RgbdSource(tmp_path)


def test_missing_and_empty_folders(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="rgb-d folder: expected a directory, found nothing at"):
        RgbdSource(tmp_path / "nope")
    with pytest.raises(SourceError, match=r"expected depth frames \(7scenes layout\), found none"):
        RgbdSource(tmp_path)
    with pytest.raises(
        SourceSpecError, match="layout: expected 'auto', '7scenes' or 'tum', found 'kinect'"
    ):
        RgbdSource(tmp_path, layout="kinect")
    bad = tmp_path / "K.txt"
    bad.write_text("585 0 320\n0 585 240\n")
    with pytest.raises(ParseError, match=r"K\.txt: expected 3 rows of 3 numbers, found 2 rows"):
        read_matrix(bad, (3, 3))


@needs_kitchen
def test_a_selection_of_no_frames_is_a_spec_error() -> None:
    """start/stop/step that select none of the frames: an empty map written as a success
    before."""
    for options in ({"start": 50}, {"start": 10, "stop": 10}, {"stop": -60}):
        with pytest.raises(
            SourceSpecError,
            match=r"start/stop/step: expected a selection of at least one of the 50 frames, "
            r"found none \(start",
        ):
            RgbdSource(KITCHEN, **options)
    assert len(RgbdSource(KITCHEN, start=49)) == 1
