"""rmw_zenoh's wire format as rmw_zenoh's design document gives it: keys, tokens, QoS, attachments,
type names and hashes."""

from __future__ import annotations

import struct

import pytest
import zenoh.ext

from plugins import rmw

pytest.importorskip("rosbags")

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_type_hash_and_keys_match_the_design_documents_examples() -> None:
    assert rmw.type_hash("std_msgs/msg/String") == STRING_HASH
    assert (
        rmw.data_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH)
        == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert rmw.any_type_key(0, "/scan") == "0/scan/*/*"
    assert rmw.type_of_key(f"0/a/b/std_msgs::msg::dds_::String_/{rmw.NO_HASH}") == (
        "std_msgs/msg/String",
        rmw.NO_HASH,
    )
    zid = "8b20917502ee955ac4476e0266340d5c"
    token = rmw.endpoint_token(
        2, zid, 0, 10, rmw.PUBLISHER, "", "talker", "/chatter", "std_msgs/msg/String",
        STRING_HASH, "::,7:,:,:,,",
    )  # fmt: skip
    assert token == (
        f"@ros2_lv/2/{zid}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,"
    )
    assert rmw.node_token(2, zid, 0, "", "listener") == f"@ros2_lv/2/{zid}/0/0/NN/%/%/listener"
    endpoint = rmw.parse_endpoint(token)
    assert (endpoint.kind, endpoint.topic, endpoint.ros_type) == (
        "MP",
        "/chatter",
        "std_msgs/msg/String",
    )
    assert rmw.qos_text(reliable=True, transient_local=True, depth=1) == "1:1:1,1:,:,:,,"
    assert rmw.qos_text(reliable=False, depth=5) == "2:2:1,5:,:,:,,"


@pytest.mark.parametrize("bad", ["", "/", "a b", "scan/*", "x//y"])
def test_topic_names_that_are_no_keys_are_refused(bad: str) -> None:
    with pytest.raises(rmw.RmwError, match="expected a ROS 2 topic name"):
        rmw.topic_name(bad)


@pytest.mark.parametrize("bad", ["String", "std_msgs::msg::String_", "a::b::dds_::_"])
def test_malformed_type_names_are_refused(bad: str) -> None:
    with pytest.raises(rmw.RmwError, match="type name"):
        rmw.ros_type(bad)


def test_attachment_is_zenoh_ext_serialised_seq_time_gid() -> None:
    gid = bytes(range(16))
    ours = rmw.Attachment(7, 1_700_000_000_123_456_789, gid).encode()
    theirs = zenoh.ext.z_serialize(
        (zenoh.ext.Int64(7), zenoh.ext.Int64(1_700_000_000_123_456_789), gid)
    ).to_bytes()
    assert ours == theirs and len(ours) == 33
    assert rmw.decode_attachment(ours) == rmw.Attachment(7, 1_700_000_000_123_456_789, gid)


def test_the_legacy_labelled_attachment_is_read_too() -> None:
    gid = b"\xaa" * 16
    legacy = zenoh.ext.z_serialize(
        (
            "sequence_number",
            zenoh.ext.Int64(3),
            "source_timestamp",
            zenoh.ext.Int64(42),
            "source_gid",
            gid,
        )
    ).to_bytes()
    assert len(legacy) == rmw.LEGACY_ATTACHMENT_SIZE == 77
    assert rmw.decode_attachment(legacy) == rmw.Attachment(3, 42, gid)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (None, "found none"),
        (b"\x00" * 20, "expected 33 bytes"),
        (struct.pack("<qqB16s", 1, 2, 15, b"\x00" * 16), "length byte 15"),
        (b"\x0fsequence_numbeX" + b"\x00" * 61, "expected label 'sequence_number'"),
    ],
)
def test_bad_attachments_say_what_was_expected(data: bytes | None, match: str) -> None:
    with pytest.raises(rmw.RmwError, match=match):
        rmw.decode_attachment(data)
