"""Hostile heartbeats: the CPU a receiver spends on one it refuses for its signature."""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

from colonyd.bench.files import write_results
from protocol import fields
from protocol.codec import COMPRESSION_SHIFT, COMPRESSION_ZSTD, FLAG_SIGNED, MAGIC, PREFIX
from protocol.errors import ProtocolError
from protocol.identity import Signer, Trust
from protocol.messages import PROTOCOL_VERSION, Heartbeat
from protocol.receiver import Receiver

#: Objects of the padded heartbeat's unknown key (receivers ignore unknown keys): ~1 MB of
#: msgpack, 965 arrays of 1024 fixints, within the decoder's 1,000,000 objects.
PAD_ARRAYS = 965


def _frame(body: dict[str, Any], origin: str, seq: int, signer: Signer) -> bytes:
    """A heartbeat frame of `body` (any keys) from `origin`, signed by `signer`, zstd body."""
    packed = fields.compress(fields.pack(body))
    flags = (COMPRESSION_ZSTD << COMPRESSION_SHIFT) | FLAG_SIGNED
    envelope = fields.pack([origin, 7, seq, 1.7e9, packed])
    frame = PREFIX.pack(MAGIC, PROTOCOL_VERSION, Heartbeat.TYPE, flags, 0) + envelope
    return frame + signer.sign(frame)


def bodies(claimed: bytes) -> dict[str, dict[str, Any]]:
    """The hostile bodies: the largest valid heartbeat (4096 layers, 4096 forgotten agents, the
    key `claimed`), and one padded with an unknown key of ~1 million msgpack objects."""
    layers = [
        {"origin": f"agent-{i:05d}-" + "x" * 48, "epoch": 2**62 + i, "version": 2**62 + i,
         "half_life": 3600.0}
        for i in range(4096)
    ]  # fmt: skip
    head = {"kind": "robot", "frame_id": "evil.odom", "identity": claimed}
    return {
        "full": {**head, "layers": layers, "forgotten": [f"gone-{i:05d}" for i in range(4096)]},
        "padded": {**head, "pad": [[1] * 1024 for _ in range(PAD_ARRAYS)]},
    }


def measure(repeat: int) -> list[dict[str, Any]]:
    """CPU (thread time) per refused heartbeat, by body and by whether its origin is pinned
    (pinned: the pinned key is known; stranger: trust on first use, the key in the body)."""
    real, forger = Signer.generate(), Signer.generate()
    out = []
    for name, body in bodies(real.public).items():
        for pinned in (True, False):
            trust = Trust("tofu", {"evil": real.public} if pinned else {})
            receiver = Receiver(own="me", trust=trust)
            frames = [_frame(body, "evil", 10 + i, forger) for i in range(repeat)]
            cpu = []
            reasons = set()
            for frame in frames:
                t0 = time.thread_time()
                try:
                    receiver.decode(frame)
                    reasons.add("accepted")
                except ProtocolError as exc:
                    reasons.add(exc.reason)
                cpu.append(time.thread_time() - t0)
            out.append(
                {
                    "body": name,
                    "origin": "pinned" if pinned else "stranger",
                    "frame_bytes": len(frames[0]),
                    "body_bytes": len(fields.pack(body)),
                    "repeat": repeat,
                    "cpu_ms_median": 1000 * statistics.median(cpu),
                    "cpu_ms_min": 1000 * min(cpu),
                    "refused_as": sorted(reasons),
                }
            )
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=20, help="frames per case")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    results = measure(args.repeat)
    for r in results:
        print(
            f"{r['body']:7s} {r['origin']:8s} {r['frame_bytes']:8d} B frame "
            f"{r['body_bytes']:8d} B body  median {r['cpu_ms_median']:8.2f} ms  "
            f"min {r['cpu_ms_min']:8.2f} ms  refused as {','.join(r['refused_as'])}"
        )
    if args.json is not None:
        write_results(args.json, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
