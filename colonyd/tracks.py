"""Tracks: what an observer saw of each member of a local colony over time, from its status (the
sim's truth in it only to evaluate), and the trajectory errors computed from them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from colonyd.mapping import tum_line

#: Least seconds between two recorded poses of one member.
SAMPLE_S = 0.2


@dataclass
class Track:
    """One member as seen through its status: estimated and true sensor poses over time."""

    carries: str
    joined: float  # seconds since the run began
    times: list[float] = field(default_factory=list)
    estimate: list[np.ndarray] = field(default_factory=list)  # sensor pose, own frame
    truth: list[np.ndarray] = field(default_factory=list)  # sensor pose, world (evaluation)
    errors: list[tuple[float, float]] = field(default_factory=list)  # (t, daemon's pose error m)
    frames: list[int] = field(default_factory=list)  # frames mapped at each recorded pose
    aligned_at: float | None = None  # first status that shows it aligned with a peer
    aligned_frame: int | None = None  # frames it had mapped by then
    caught_up_at: float | None = None
    sent: int = 0
    received: int = 0


def in_contact(report: dict[str, Any]) -> bool:
    """True when a daemon's status shows its own frame aligned with a peer's: it is in its colony
    frame with another member, or one of its own alignment attempts was accepted and confirmed
    (with an anchor, a pair aligned with each other but not with the anchor is outside the colony
    frame yet)."""
    agent = report["agent"]
    frame = report.get("colony_frame", {})
    members = frame.get("agents", {})
    if agent in members and len(members) > 1:
        return True
    return any(
        a.get("aligned") and not a.get("provisional")
        for a in (report.get("alignments") or {}).values()
    )


def record(reports: list[dict[str, Any]], tracks: dict[str, Track], now: float) -> None:
    """Add what `reports` (one status round, at `now` seconds into the run) say to the tracks.

    A pose is recorded when the member has moved or turned since the last one (a fixed camera,
    or a robot whose source is done, adds no repeated samples that would weigh in the ATE)."""
    for r in reports:
        track = tracks.get(r["agent"])
        if track is None:
            continue
        counts = r["metrics"]["counts"]
        track.sent = int(counts.get("bytes_published", 0)) + int(counts.get("bytes_served", 0))
        track.received = int(counts.get("bytes_received", 0))
        if r.get("pose_matrix") is not None and r.get("truth_matrix") is not None:
            truth = np.array(r["truth_matrix"])
            moved = not track.truth or not np.allclose(truth, track.truth[-1], atol=1e-9)
            if moved and (not track.times or now - track.times[-1] >= SAMPLE_S):
                track.times.append(now)
                track.estimate.append(np.array(r["pose_matrix"]))
                track.truth.append(truth)
                track.frames.append(int(counts.get("frames", 0)))
        if r.get("pose_error_m") is not None:
            track.errors.append((now, float(r["pose_error_m"])))
        if track.aligned_at is None and in_contact(r):
            track.aligned_at = now
            track.aligned_frame = int(counts.get("frames", 0))


def caught_up(reports: list[dict[str, Any]], agent: str) -> bool:
    """True when `agent` holds every other member's layer at the version its origin reports."""
    mine = next((r for r in reports if r["agent"] == agent), None)
    if mine is None:
        return False
    for r in reports:
        own = r.get("layers", {}).get(r["agent"])
        if r["agent"] == agent or not own or not own.get("seq"):
            continue
        have = mine.get("layers", {}).get(r["agent"])
        if have is None or have["seq"] < own["seq"]:
            return False
    return True


def pose_errors(track: Track) -> np.ndarray | None:
    """Per recorded pose, the position error after the rigid Umeyama fit of the whole estimated
    path onto the true one (what `evo_ape tum GT EST -a` plots); None below 3 poses."""
    if len(track.truth) < 3:
        return None
    from voxel.localisation.metrics import absolute_trajectory_error

    ate = absolute_trajectory_error(np.array(track.truth), np.array(track.estimate))
    errors: np.ndarray = ate.errors
    return errors


def ate(track: Track) -> float | None:
    """ATE RMSE (m) of the recorded estimate against the truth, or None below 3 poses."""
    errors = pose_errors(track)
    return None if errors is None else float(np.sqrt(np.mean(errors**2)))


def write_tum(track: Track, directory: Path, stem: str) -> dict[str, Path]:
    """`<stem>.estimate.tum` and `<stem>.groundtruth.tum` of the recorded poses (time: seconds
    since the run began); nothing when no pose was recorded."""
    if not track.estimate:
        return {}
    directory.mkdir(parents=True, exist_ok=True)
    files = {
        "estimate": directory / f"{stem}.estimate.tum",
        "groundtruth": directory / f"{stem}.groundtruth.tum",
    }
    for name, poses in (("estimate", track.estimate), ("groundtruth", track.truth)):
        files[name].write_text(
            "".join(tum_line(t, p) + "\n" for t, p in zip(track.times, poses, strict=True))
        )
    return files
