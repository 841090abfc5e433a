"""Faults on one machine: network namespaces and veth links, a small tmpfs, a busy core, hostile
frames.

Everything here needs no daemon internals: it acts on processes, links and mounts from outside,
as an operator (or a failing robot) would. What needs root says so (`need_root`) and cleans up
after itself, also when the caller fails.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import threading
import uuid
from collections import defaultdict
from pathlib import Path
from typing import Any, Self

import numpy as np

from voxel import keys as vk
from voxel.delta import Delta


def need_root(what: str) -> str:
    """Why `what` cannot run here ("" if it can): root and the `ip` / `mount` tools."""
    if os.geteuid() != 0:
        return f"{what} needs root (network namespaces, mounts); running as uid {os.geteuid()}"
    missing = [t for t in ("ip", "mount", "umount") if shutil.which(t) is None]
    if missing:
        return f"{what} needs the tools {', '.join(missing)}"
    return ""


def _run(*cmd: str) -> None:
    out = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=20)
    if out.returncode != 0:
        msg = f"{' '.join(cmd)} failed ({out.returncode}): {out.stderr.strip()}"
        raise RuntimeError(msg)


# ------------------------------------------------------------------------------- processes


def peak_rss_mb(pid: int) -> float:
    """The peak resident set size of a process so far (VmHWM), MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return 0.0


class Spinner:
    """Another process keeping one core busy (a pure-Python loop), stopped by its PID; in a
    session of its own, so that it takes its core from the machine, not from the share of the
    session that started it (autogroup, docs/RELIABILITY.md)."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen[bytes] | None = None

    def __enter__(self) -> Self:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", "while True: pass"],
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


# ------------------------------------------------------------------------------------ disk


class Tmpfs:
    """A tmpfs of `size_mb` MiB mounted on `path` (root only); unmounted on exit."""

    def __init__(self, path: Path, size_mb: float) -> None:
        self.path = Path(path)
        self.size_kb = int(size_mb * 1024)

    def __enter__(self) -> Self:
        self.path.mkdir(parents=True, exist_ok=True)
        _run(
            "mount", "-t", "tmpfs", "-o", f"size={self.size_kb}k,mode=0755", "tmpfs", str(self.path)
        )
        return self

    def fill(self, leave_kb: int = 0) -> Path:
        """Fill the filesystem (leaving about `leave_kb` KiB); returns the filler file."""
        filler = self.path / "filler"
        with open(filler, "ab") as fh:
            chunk = b"\0" * 65536
            try:
                while True:
                    st = os.statvfs(self.path)
                    free = st.f_bavail * st.f_frsize - leave_kb * 1024
                    if free <= 0:
                        break
                    fh.write(chunk[: min(len(chunk), free)])
                    fh.flush()
            except OSError:
                pass
        return filler

    def free(self) -> None:
        (self.path / "filler").unlink(missing_ok=True)

    def remount(self, *, read_only: bool) -> None:
        _run("mount", "-o", f"remount,{'ro' if read_only else 'rw'}", str(self.path))

    def __exit__(self, *exc: object) -> None:
        out = subprocess.run(
            ["umount", str(self.path)], check=False, capture_output=True, timeout=20
        )
        if out.returncode != 0:
            subprocess.run(
                ["umount", "-l", str(self.path)], check=False, capture_output=True, timeout=20
            )


# --------------------------------------------------------------------------------- network


class NetLab:
    """Network namespaces, one per daemon, on a bridge in a "switch" namespace, plus a leg from
    the root namespace (the observer). `cut(name)` takes a daemon's link down; `heal(name)`
    brings it back. Addresses are 10.<net>.0.<i+1>/24; the root leg is .254.

    Names carry a random tag, so parallel runs never meet; `close()` stops nothing but removes
    every namespace and link made (namespaces hold their veth ends, so deleting them is enough).
    """

    def __init__(self, names: list[str], net: int = 213) -> None:
        self.tag = uuid.uuid4().hex[:5]
        self.names = list(names)
        self.net = net
        self.switch = f"cfs{self.tag}"
        self.made: list[str] = []
        self.root_leg = f"cfr{self.tag}"
        self.hosts = {n: f"10.{net}.0.{i + 1}" for i, n in enumerate(names)}

    def ns(self, name: str) -> str:
        return f"cf{self.tag}{self.names.index(name)}"

    def prefix(self, name: str) -> list[str]:
        """Command prefix that runs a process inside `name`'s namespace."""
        return ["ip", "netns", "exec", self.ns(name)]

    def _port(self, name: str) -> str:
        return f"cfp{self.tag}{self.names.index(name)}"

    def __enter__(self) -> Self:
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def _build(self) -> None:
        sw = self.switch
        _run("ip", "netns", "add", sw)
        self.made.append(sw)
        _run("ip", "-n", sw, "link", "add", "br0", "type", "bridge")
        _run("ip", "-n", sw, "link", "set", "br0", "up")
        _run("ip", "-n", sw, "link", "set", "lo", "up")
        for i, name in enumerate(self.names):
            ns = self.ns(name)
            _run("ip", "netns", "add", ns)
            self.made.append(ns)
            port = self._port(name)
            _run("ip", "link", "add", port, "type", "veth", "peer", "name", f"cfe{self.tag}{i}")
            _run("ip", "link", "set", port, "netns", sw)
            _run("ip", "link", "set", f"cfe{self.tag}{i}", "netns", ns)
            _run("ip", "-n", ns, "link", "set", f"cfe{self.tag}{i}", "name", "eth0")
            _run("ip", "-n", ns, "addr", "add", f"{self.hosts[name]}/24", "dev", "eth0")
            _run("ip", "-n", ns, "link", "set", "eth0", "up")
            _run("ip", "-n", ns, "link", "set", "lo", "up")
            _run("ip", "-n", sw, "link", "set", port, "master", "br0")
            _run("ip", "-n", sw, "link", "set", port, "up")
        # The observer's leg from the root namespace (never cut).
        _run("ip", "link", "add", self.root_leg, "type", "veth", "peer", "name", f"cfq{self.tag}")
        self.made.append(self.root_leg)
        _run("ip", "link", "set", f"cfq{self.tag}", "netns", sw)
        _run("ip", "-n", sw, "link", "set", f"cfq{self.tag}", "master", "br0")
        _run("ip", "-n", sw, "link", "set", f"cfq{self.tag}", "up")
        _run("ip", "addr", "add", f"10.{self.net}.0.254/24", "dev", self.root_leg)
        _run("ip", "link", "set", self.root_leg, "up")

    def cut(self, name: str) -> None:
        """Take `name`'s link down at the switch: its packets go nowhere, nothing is reset."""
        _run("ip", "-n", self.switch, "link", "set", self._port(name), "down")

    def heal(self, name: str) -> None:
        _run("ip", "-n", self.switch, "link", "set", self._port(name), "up")

    def close(self) -> None:
        for made in reversed(self.made):
            if made == self.root_leg:
                subprocess.run(
                    ["ip", "link", "del", made], check=False, capture_output=True, timeout=20
                )
            else:
                subprocess.run(
                    ["ip", "netns", "del", made], check=False, capture_output=True, timeout=20
                )
        self.made.clear()

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------- delta content checks


def delta_digest(delta: Delta) -> str:
    """Hash of a delta's voxels (keys, log-odds, last times, channels), independent of order
    and of its version labels: equal for a logged record and the frame that carried it."""
    packed = vk.pack(delta.keys)
    order = np.argsort(packed, kind="stable")
    h = hashlib.sha256()
    h.update(packed[order].tobytes())
    h.update(np.ascontiguousarray(delta.logodds[order]).tobytes())
    h.update(np.ascontiguousarray(delta.last_time[order]).tobytes())
    for name in sorted(delta.channels):
        h.update(name.encode() + b"\0")
        h.update(np.ascontiguousarray(delta.channels[name][order]).tobytes())
    return h.hexdigest()[:20]


class DeltaWatch:
    """Records the content digest of every delta frame an origin publishes, per (epoch, seq):
    a seq given two contents shows up as two digests."""

    def __init__(self, session: Any, namespace: str, origin: str) -> None:
        from protocol import Receiver, VoxelDelta
        from protocol.keyexpr import topic_key

        self._receiver = Receiver()  # checks frames, not signatures: we only read contents
        self._cls = VoxelDelta
        self._lock = threading.Lock()
        self.seen: dict[tuple[int, int, int], set[str]] = defaultdict(set)
        self.undecodable = 0
        self._sub = session.declare_subscriber(topic_key(namespace, origin, "delta"), self._on)

    def _on(self, sample: Any) -> None:
        try:
            msg = self._receiver.decode(sample.payload.to_bytes())
        except Exception:  # noqa: BLE001 - counted; a watcher never stops
            with self._lock:
                self.undecodable += 1
            return
        if isinstance(msg, self._cls):
            d = msg.delta
            with self._lock:
                self.seen[(msg.epoch, d.to_version, msg.part)].add(delta_digest(d))

    def seqs(self, epoch: int) -> set[int]:
        with self._lock:
            return {s for (e, s, _p) in self.seen if e == epoch}

    def digest(self, epoch: int, seq: int) -> set[str]:
        with self._lock:
            return set(self.seen.get((epoch, seq, 0), set()))

    def reused(self) -> int:
        """(epoch, seq, part) seen with more than one content."""
        with self._lock:
            return sum(1 for v in self.seen.values() if len(v) > 1)

    def close(self) -> None:
        self._sub.undeclare()
