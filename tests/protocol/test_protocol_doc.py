"""docs/PROTOCOL.md's worked example is what the code produces, and decodes to what the doc says."""

from __future__ import annotations

import json
import re
from pathlib import Path

import msgpack
import numpy as np

from protocol.codec import decode
from protocol.deltacodec import decode_delta, encode_delta
from protocol.example import (
    EXAMPLE_KEY,
    example_frame,
    example_message,
    example_surface_channel,
    example_surface_delta,
    hexdump,
)
from protocol.messages import VoxelDelta

DOC = Path(__file__).resolve().parents[2] / "docs" / "PROTOCOL.md"


def _block(marker: str) -> str:
    match = re.search(rf"<!-- {marker} -->\s*```[a-z]*\n(.*?)```", DOC.read_text(), re.S)
    assert match, f"{marker} block missing from {DOC}"
    return match.group(1)


def _hex(marker: str) -> bytes:
    lines = _block(marker).strip().splitlines()
    return bytes.fromhex(" ".join(re.sub(r"^[0-9a-f]{4}  ", "", line) for line in lines))


def test_doc_hex_is_what_the_code_encodes() -> None:
    frame = _hex("example-frame")
    assert frame == example_frame(), "regenerate the example: hexdump(example_frame())\n" + hexdump(
        example_frame()
    )
    assert len(frame) == 230


def test_doc_hex_decodes_to_documented_values() -> None:
    msg = decode(_hex("example-frame"))
    assert isinstance(msg, VoxelDelta)
    assert (msg.origin, msg.epoch, msg.seq, msg.time, msg.frame_id) == (
        "r1",
        1,
        7,
        1_700_000_000.5,
        "map",
    )
    assert (msg.delta.from_version, msg.delta.to_version, msg.delta.resolution) == (41, 42, 0.05)
    expected = json.loads(_block("example-decoded"))
    np.testing.assert_array_equal(msg.delta.keys, expected["keys"])
    np.testing.assert_array_equal(
        msg.delta.logodds, np.array(expected["logodds"], dtype=np.float32)
    )
    np.testing.assert_array_equal(msg.delta.last_time, expected["last_time"])
    np.testing.assert_array_equal(msg.delta.channels["hits"], expected["hits"])
    original = example_message().delta
    assert np.all(np.abs(np.sort(original.logodds) - np.sort(msg.delta.logodds)) <= 2.0**-7)


def test_doc_tag_authenticates_the_example() -> None:
    tag = _hex("example-tag")
    signed = bytearray(_hex("example-frame"))
    signed[6] = 0x01
    frame = bytes(signed) + tag
    assert frame == example_frame(EXAMPLE_KEY)
    assert isinstance(decode(frame, key=EXAMPLE_KEY), VoxelDelta)


def test_doc_sparse_surface_channel_is_what_the_code_encodes_and_decodes() -> None:
    entry = _hex("example-surface-channel")
    assert entry == example_surface_channel(), "regenerate: hexdump(example_surface_channel())"
    body = msgpack.unpackb(encode_delta(example_surface_delta()))
    body["ch"] = [c for c in body["ch"] if c[0] != "surface"] + [msgpack.unpackb(entry)]
    back = decode_delta(msgpack.packb(body))
    assert back.surface_mask is not None and back.surface_mask.tolist() == [True, False, False]
    assert back.keys[0].tolist() == [2, 3, 4]
    assert back.channels["surface"].tolist() == [[16, -32, 127], [0, 0, 0], [0, 0, 0]]
