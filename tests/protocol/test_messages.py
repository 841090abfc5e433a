"""Tests of protocol.messages: validation at construction, conversions, the type registry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from protocol.messages import (
    MESSAGE_TYPES,
    AlignOffer,
    Announce,
    DeltaRangeRequest,
    Heartbeat,
    LayerVersion,
    ObjectCentroid,
    Pose,
    PoseFix,
    SensorInfo,
    SnapshotReply,
    SnapshotRequest,
    VoxelDelta,
)
from tests.protocol.helpers import make_delta, sample_messages
from voxel.sensor import SensorModel

COMMON = {"origin": "r1", "time": 1.0}


def test_every_type_has_a_unique_code_and_kind() -> None:
    assert sorted(MESSAGE_TYPES) == list(range(1, 14))
    assert len({c.KIND for c in MESSAGE_TYPES.values()}) == 13
    assert {type(m) for m in sample_messages()} == set(MESSAGE_TYPES.values())


def test_sensor_info_round_trips_a_sensor_model() -> None:
    model = SensorModel(prob_hit=0.8, prob_miss=0.3, max_range=12.0, kind="lidar3d")
    assert SensorInfo.from_model("top", model).to_model() == model
    unlimited = SensorInfo.from_model("cam", SensorModel())
    assert unlimited.max_range is None and math.isinf(unlimited.to_model().max_range)


@pytest.mark.parametrize(
    ("factory", "match"),
    [
        (
            lambda: Pose(**COMMON, frame_id="m", position=(0, 0, 0), orientation=(0, 0, 0, 2)),
            "unit quaternion",
        ),
        (lambda: Pose(**COMMON, frame_id="m", position=(0, 0, float("nan"))), "finite"),
        (
            lambda: Pose(**COMMON, frame_id="m", position=(0, 0, 0), covariance=[0.0] * 35),
            "at least 36",
        ),
        (lambda: Pose(origin="bad origin", time=1.0, frame_id="m", position=(0, 0, 0)), "pattern"),
        (lambda: Pose(**COMMON, frame_id="m", position=(0, 0, 0), typo=1), "Extra inputs"),
        (
            lambda: Pose(**COMMON, epoch=-1, frame_id="m", position=(0, 0, 0)),
            "greater than or equal",
        ),
        (lambda: Announce(**COMMON, kind="ground", frame_id="m", resolution=0.0), "greater than 0"),
        (lambda: SensorInfo(name="s", kind="sonar"), "sensor kind must be one of"),
        (lambda: SensorInfo(name="s", kind="depth", prob_hit=1.5), "less than 1"),
        (
            lambda: ObjectCentroid(
                object_id=1, class_id=70000, position=(0, 0, 0), voxel_count=1, time=0.0
            ),
            "65535",
        ),
        (
            lambda: VoxelDelta(
                **COMMON,
                frame_id="m",
                delta=make_delta(np.random.default_rng(0), 5),
                part=2,
                parts=2,
            ),
            "part must be below parts",
        ),
        (lambda: VoxelDelta(**COMMON, frame_id="m", delta="not a delta"), "instance of Delta"),
        (
            lambda: DeltaRangeRequest(
                **COMMON, layer="r", request_id=1, from_version=5, to_version=4
            ),
            "to_version",
        ),
        (
            lambda: SnapshotRequest(**COMMON, layer="r", request_id=1, max_part_bytes=10),
            "greater than or equal",
        ),
        (
            lambda: SnapshotRequest(**COMMON, layer="r", request_id=1, timeout_ms=1 << 32),
            "less than or equal",
        ),
        (
            lambda: SnapshotReply(
                **COMMON,
                layer="r",
                request_id=1,
                frame_id="m",
                delta=make_delta(np.random.default_rng(0), 5),
            ),
            "layer_epoch",
        ),
        (
            lambda: Heartbeat(
                **COMMON,
                kind="ground",
                frame_id="m",
                layers=[
                    LayerVersion(origin="a", epoch=1, version=2),
                    LayerVersion(origin="a", epoch=1, version=3),
                ],
            ),
            "each origin once, found 'a' twice",
        ),
        (
            lambda: Heartbeat(**COMMON, kind="ground", frame_id="m", layers=[{"origin": "a"}]),
            "epoch",
        ),
        (lambda: Pose(**COMMON, epoch=1 << 63, frame_id="m", position=(0, 0, 0)), "less than"),
        (
            lambda: PoseFix(**COMMON, target="r1", frame_id="m", stamp=1.0, position=(0, 0, 0)),
            "another agent than the origin, found 'r1' for both",
        ),
        (lambda: PoseFix(**COMMON, target="r2", frame_id="m", position=(0, 0, 0)), "stamp"),
        (
            lambda: PoseFix(
                **COMMON, target="r2", frame_id="m", stamp=float("inf"), position=(0, 0, 0)
            ),
            "finite",
        ),
        (
            lambda: PoseFix(
                **COMMON, target="r2", frame_id="m", stamp=1.0, position=(0, 0, 0), confidence=2
            ),
            "less than or equal to 1",
        ),
        (
            lambda: PoseFix(**COMMON, target="a/b", frame_id="m", stamp=1.0, position=(0, 0, 0)),
            "pattern",
        ),
    ],
)
def test_invalid_messages_rejected(factory, match: str) -> None:
    with pytest.raises(ValidationError, match=match):
        factory()


def test_rigid_matrix_conversions() -> None:
    angle = 0.7
    t = np.eye(4)
    t[:3, :3] = [
        [math.cos(angle), -math.sin(angle), 0],
        [math.sin(angle), math.cos(angle), 0],
        [0, 0, 1],
    ]
    t[:3, 3] = [1.0, 2.0, 3.0]
    pose = Pose(**COMMON, frame_id="m", **Pose.split_matrix(t))
    np.testing.assert_allclose(pose.matrix(), t, atol=1e-12)
    for r in (
        [[1, 0, 0], [0, -1, 0], [0, 0, -1]],
        [[-1, 0, 0], [0, 1, 0], [0, 0, -1]],
        [[-1, 0, 0], [0, -1, 0], [0, 0, 1]],
    ):
        m = np.eye(4)
        m[:3, :3] = r
        offer = AlignOffer(
            **COMMON, target="r2", source_frame="a", target_frame="b", **AlignOffer.split_matrix(m)
        )
        np.testing.assert_allclose(offer.matrix(), m, atol=1e-12)
    with pytest.raises(ValueError, match="4x4"):
        Pose.split_matrix(np.eye(3))


def test_voxel_delta_exact_flag() -> None:
    msg = VoxelDelta(**COMMON, frame_id="m", delta=make_delta(np.random.default_rng(0), 5))
    assert msg.exact
