"""Agent identities: signed frames, trust on first use, trust lists, impersonation refused."""

from __future__ import annotations

import pytest

from protocol.codec import decode, encode
from protocol.errors import (
    IdentityError,
    NotIntroducedError,
    ProtocolError,
    UnknownIdentityError,
)
from protocol.identity import MAX_PINS, Signer, Trust, parse_public, verify_signature
from protocol.messages import DeltaRangeRequest, Heartbeat, LayerVersion, Pose
from protocol.receiver import Receiver
from tests.protocol.helpers import KEY
from tests.shared import fresh_process

A, B = Signer.generate(), Signer.generate()


def _hb(seq: int, signer: Signer | None, origin: str = "a", identity: bytes | None = None) -> bytes:
    msg = Heartbeat(
        origin=origin,
        epoch=1,
        seq=seq,
        time=1.0,
        kind="robot",
        frame_id="map",
        identity=identity if identity is not None else (signer.public if signer else None),
    )
    return encode(msg, key=KEY, signer=signer)


def _pose(seq: int, signer: Signer | None, origin: str = "a") -> bytes:
    return encode(
        Pose(origin=origin, epoch=1, seq=seq, time=1.0, frame_id="map", position=(0.0, 0.0, 0.0)),
        key=KEY,
        signer=signer,
    )


def test_signatures_verify_and_tampering_is_caught() -> None:
    frame = _pose(1, A)
    assert decode(frame, key=KEY, trust=Trust("list", {"a": A.public})).origin == "a"
    with pytest.raises(IdentityError, match="does not verify") as info:
        decode(frame, key=KEY, trust=Trust("list", {"a": B.public}))
    assert info.value.reason == "identity"
    with pytest.raises(IdentityError, match="does not verify"):
        verify_signature(A.public, b"other data", A.sign(b"data"), "a")
    assert decode(frame, key=KEY).origin == "a"  # without a trust the signature is not checked


def test_trust_on_first_use_pins_at_accept_and_refuses_another_key() -> None:
    pinned: list[tuple[str, bytes]] = []
    rx = Receiver(key=KEY, trust=Trust("tofu", on_pin=lambda a, k: pinned.append((a, k))))
    with pytest.raises(NotIntroducedError, match="expected its heartbeat first") as early:
        rx.decode(_pose(1, A))  # nothing known of 'a' yet
    assert early.value.reason == "unknown_identity"  # counted as before; a daemon logs it as info
    rx.decode(_hb(2, A))  # checked with the key it carries, not yet accepted: nothing pinned
    assert pinned == [] and rx.trust.pins() == {}
    rx.receive(_hb(3, A))
    assert pinned == [("a", A.public)] and rx.trust.pins() == {"a": A.public}
    rx.receive(_pose(4, A))
    with pytest.raises(IdentityError, match="does not verify") as info:
        rx.decode(_hb(5, B))  # another key holder claiming to be 'a': checked with a's pin
    assert info.value.reason == "identity"
    with pytest.raises(IdentityError, match="expected its pinned key"):
        rx.decode(_hb(8, A, identity=B.public))  # a's signature, offering another key
    with pytest.raises(IdentityError, match="does not verify"):
        rx.decode(_hb(6, B, identity=A.public))  # claims a's key, cannot sign with it
    with pytest.raises(IdentityError, match="found none"):
        rx.decode(_pose(7, None))  # unsigned
    assert rx.rejected == {"unknown_identity": 1, "identity": 4}


def test_requests_need_no_signature_and_off_checks_nothing() -> None:
    rx = Receiver(key=KEY, trust=Trust("list", {}))
    request = DeltaRangeRequest(
        origin="peer",
        epoch=1,
        seq=1,
        time=1.0,
        layer="a",
        request_id=1,
        from_version=0,
        to_version=3,
    )
    rx.receive(encode(request, key=KEY))
    with pytest.raises(UnknownIdentityError, match="trust list") as listed:
        rx.decode(_hb(1, A))  # a list admits only the agents on it, heartbeat or not
    assert not isinstance(listed.value, NotIntroducedError)  # a refusal to warn about
    off = Receiver(key=KEY, trust=Trust("off"))
    off.receive(_pose(1, None))
    off.receive(_hb(2, B))
    assert off.trust.pins() == {}


def test_bad_keys_and_modes_are_refused() -> None:
    with pytest.raises(IdentityError, match="64 hex digits, found 'abc'"):
        parse_public("abc", "trusted_keys['a']")
    with pytest.raises(IdentityError, match="trust mode must be one of"):
        Trust("sometimes")  # type: ignore[arg-type]
    with pytest.raises(IdentityError, match="expected 32 raw Ed25519 private key bytes, found 3"):
        Signer.from_bytes(b"abc")
    assert Signer.from_bytes(A.private_bytes()).public == A.public


def test_keys_are_raw_bytes_without_the_key_serialization_modules() -> None:
    """Raw key bytes come from the key objects themselves: cryptography's serialization package
    (SSH, PKCS, ciphers: ~30 ms of CPU) is not imported by the daemon. A fresh process signs and
    verifies, then checks the bytes against that package's raw encodings."""

    code = (
        "import sys\n"
        "import colonyd.daemon, colonyd.cli\n"
        "from protocol.identity import Signer, verify_signature\n"
        "s = Signer.generate()\n"
        "again = Signer.from_bytes(s.private_bytes())\n"
        "verify_signature(again.public, b'data', s.sign(b'data'), 'a')\n"
        "SER = 'cryptography.hazmat.primitives.serialization'\n"
        "print(SER in sys.modules, len(s.public), again.public == s.public)\n"
        "from cryptography.hazmat.primitives import serialization as ser\n"
        "raw = ser.Encoding.Raw\n"
        "key = s._key\n"
        "print(key.private_bytes(raw, ser.PrivateFormat.Raw, ser.NoEncryption())\n"
        "      == s.private_bytes(), key.public_key().public_bytes(raw, ser.PublicFormat.Raw)\n"
        "      == s.public)\n"
    )
    stdout = fresh_process(code)
    assert stdout.split("\n")[:2] == ["False 32 True", "True True"], stdout


def test_trust_on_first_use_pins_a_bounded_number_of_agents() -> None:
    """An open colony (no key) trusting on first use, the default: a stranger sending heartbeats
    under ever new agent ids must not grow the pins (which a daemon writes to disk, whole, at
    every new pin) without end; past the bound a new agent is refused before anything is
    recorded, and every pin kept stays (pins loaded from disk count: here all but 3)."""
    pinned: list[str] = []
    signer = Signer.generate()
    earlier = {f"old{i}": signer.public for i in range(MAX_PINS - 3)}
    rx = Receiver(trust=Trust("tofu", earlier, on_pin=lambda agent, key: pinned.append(agent)))
    for i in range(6):
        hb = Heartbeat(
            origin=f"x{i}", epoch=1, seq=1, time=1.0, kind="robot", frame_id="map",
            identity=signer.public,
        )  # fmt: skip
        try:
            rx.receive(encode(hb, signer=signer))
        except UnknownIdentityError as exc:
            assert "expected one of the 4096 agents pinned" in str(exc), exc
    assert len(rx.trust.pins()) == MAX_PINS == 4096
    assert pinned == ["x0", "x1", "x2"]
    assert rx.rejected == {"unknown_identity": 3}
    assert rx.replay is not None and "x3" not in rx.replay._state  # refused: no window moved
    again = Heartbeat(origin="x0", epoch=1, seq=2, time=1.0, kind="robot", frame_id="map")
    rx.receive(encode(again, signer=signer))  # a pinned agent carries on


def _raw_hb(
    body: dict | bytes, origin: str, signer: Signer, seq: int = 2, zstd: bool = True
) -> bytes:
    """A Heartbeat frame of any `body` (keys the model may not know, values it refuses; bytes:
    packed already)."""
    from protocol import fields
    from protocol.codec import COMPRESSION_SHIFT, COMPRESSION_ZSTD, FLAG_SIGNED, MAGIC, PREFIX
    from protocol.messages import PROTOCOL_VERSION

    packed = body if isinstance(body, bytes) else fields.pack(body)
    packed = fields.compress(packed) if zstd else packed
    flags = ((COMPRESSION_ZSTD << COMPRESSION_SHIFT) if zstd else 0) | FLAG_SIGNED
    envelope = fields.pack([origin, 7, seq, 1.0, packed])
    frame = PREFIX.pack(MAGIC, PROTOCOL_VERSION, Heartbeat.TYPE, flags, 0) + envelope
    return frame + signer.sign(frame)


def _count_unpacks(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Bodies `decode` scans and unpacks whole (the parse work a hostile frame may cost)."""
    import protocol.codec

    calls: list[int] = []
    real = protocol.codec.fields.unpack

    def counted(data: bytes, what: str, *args: object) -> object:
        if "body" in what:  # (not the envelope: unpacked for every frame)
            calls.append(len(data))
        return real(data, what, *args)

    monkeypatch.setattr(protocol.codec.fields, "unpack", counted)
    return calls


def test_a_pinned_agents_heartbeat_is_checked_before_its_body_is_read(monkeypatch) -> None:
    """A Heartbeat carries its key in its body, so every one was decompressed, scanned,
    unpacked and validated before its signature was checked (a 286-byte frame padded with
    ~1 million msgpack objects: ~0.25 s of CPU, `colonyd.bench.hostile_heartbeat`). For an
    agent whose key is pinned the pinned key checks it first: a forged one is refused for its
    signature however broken its body, and no body is unpacked."""
    unpacked = _count_unpacks(monkeypatch)
    rx = Receiver(trust=Trust("tofu", {"a": A.public}))
    garbage = {"kind": "robot", "frame_id": "map", "layers": [{"origin": "x", "epoch": -1}]}
    for body in (garbage, {"pad": [[1] * 1024 for _ in range(100)]}):
        with pytest.raises(IdentityError, match="does not verify"):
            rx.decode(_raw_hb(body, "a", B))
    assert unpacked == []
    assert rx.decode(_raw_hb({"kind": "robot", "frame_id": "map"}, "a", A)).origin == "a"
    assert len(unpacked) == 1


def test_a_strangers_heartbeat_is_checked_before_its_body_is_parsed(monkeypatch) -> None:
    """Trust on first use: a stranger's Heartbeat offers its key in its body. Only that key is
    read (the rest of the body skipped, undecoded) and the signature checked with it before the
    body is scanned, unpacked and validated: a forged one whose layers are out of range is
    refused for its signature (it was refused for its range, after all the work)."""
    unpacked = _count_unpacks(monkeypatch)
    rx = Receiver(trust=Trust("tofu"))
    bad = [{"origin": "x", "epoch": -1, "version": 1}] * 4096
    body = {"kind": "robot", "frame_id": "map", "layers": bad, "identity": A.public}
    with pytest.raises(IdentityError, match="does not verify"):
        rx.decode(_raw_hb(body, "a", B))  # offers a's key, signed by another
    with pytest.raises(NotIntroducedError):
        rx.decode(_raw_hb({**body, "identity": "x" * 32}, "a", B))  # no key (not a bin)
    assert unpacked == []
    with pytest.raises(ProtocolError) as info:  # signed with the key it offers: parsed
        rx.decode(_raw_hb(body, "a", A))
    assert info.value.reason == "range"
    assert len(unpacked) == 1


def test_heartbeat_bodies_past_their_bound_are_refused_unread() -> None:
    """The largest valid Heartbeat body (4096 layers, 4096 forgotten agents) packs to ~0.8 MB:
    a body (compressed or not) past `Limits.max_heartbeat_bytes` (1 MiB) is refused before it
    is decompressed or read, though it were signed by its pinned key (other types keep the 64
    MiB body bound)."""
    rx = Receiver(trust=Trust("tofu", {"a": A.public}))
    pad = {"kind": "robot", "frame_id": "map", "pad": bytes(2 << 20)}
    with pytest.raises(ProtocolError) as info:
        rx.decode(_raw_hb(pad, "a", A))  # 2 MiB of zeros: a small zstd frame
    assert info.value.reason == "decompression_bomb"
    with pytest.raises(ProtocolError) as info:
        rx.decode(_raw_hb(pad, "a", A, zstd=False))
    assert info.value.reason == "oversized"
    assert rx.decode(_raw_hb({**pad, "pad": bytes(1 << 19)}, "a", A)).origin == "a"
    name, top = "a" * 64, 2**63 - 1
    largest = Heartbeat(
        origin="a", epoch=top, seq=top, time=1.0, kind=name, frame_id=name,
        position=(1e300, 1e300, 1e300), identity=A.public,
        layers=[LayerVersion(origin=f"{name[:59]}{i:05d}", epoch=top, version=top,
                             half_life=1e300) for i in range(4096)],
        forgotten=[f"{name[:59]}{i:05d}" for i in range(4096)],
    )  # fmt: skip
    for compression in ("zstd", "none"):
        frame = encode(largest, signer=A, compression=compression)
        assert len(rx.decode(frame).layers) == 4096


def test_a_strangers_heartbeat_with_keys_of_any_string_format_is_read() -> None:
    """A body is a msgpack map with string keys (PROTOCOL.md §5): a key may be any of msgpack's
    string formats (fixstr, str8, str16, str32; an encoder need not pick the shortest), and
    `unpack` takes them all. The walk that reads a stranger's `identity` before its signature
    is checked refused a str32 key (`malformed`): a valid heartbeat of another encoder refused
    from every agent not pinned yet."""
    from protocol import fields

    def str32(text: str) -> bytes:
        raw = text.encode()
        return b"\xdb" + len(raw).to_bytes(4, "big") + raw

    body = (b"\x83" + str32("kind") + fields.pack("robot") + str32("frame_id") + fields.pack("map")
            + str32("identity") + fields.pack(A.public))  # fmt: skip
    assert fields.unpack(body, "body", Receiver().limits) == {
        "kind": "robot", "frame_id": "map", "identity": A.public
    }  # fmt: skip
    hb = Receiver(trust=Trust("tofu")).decode(_raw_hb(body, "a", A))
    assert hb.origin == "a" and hb.identity == A.public


def test_a_reinstalled_agents_heartbeat_says_its_pin_may_need_removing() -> None:
    """An agent reinstalled with a new key (its pin, here or in `known_agents.json`, still the
    old one) sends heartbeats signed with the new key and offering it. They are refused, as
    they were; but its heartbeat is now checked with the pinned key before its body is read,
    and the refusal said only that the signature does not verify, where it said what the
    operator may have to do: remove the reinstalled agent's pin (or look for an impersonator).
    The refusal of a pinned agent's heartbeat says so again, with no body read for it."""
    rx = Receiver(key=KEY, trust=Trust("tofu", {"a": A.public}))
    with pytest.raises(IdentityError, match="does not verify") as info:
        rx.decode(_hb(5, B))  # 'a' reinstalled with key B
    assert "pin must be removed" in str(info.value), info.value
    with pytest.raises(IdentityError, match="does not verify") as info:
        rx.decode(_pose(6, B))  # not a heartbeat: no key offered, no hint
    assert "pin" not in str(info.value)
