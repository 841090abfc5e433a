"""Pictures of a sim colony run: the fused map from above with every robot's paths and objects,
and pose errors over time."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from voxel import keys as vk

if TYPE_CHECKING:
    from colonyd.export import MapReply
    from colonyd.tracks import Track

#: BGR colour per member, in order of appearance.
COLOURS = ((40, 110, 230), (60, 170, 60), (200, 80, 40), (160, 60, 170), (30, 170, 200))
PIXELS_PER_M = 40
MARGIN_M = 1.0


def _colour(i: int) -> tuple[int, int, int]:
    return COLOURS[i % len(COLOURS)]


class _Canvas:
    """A top-down image of the colony frame's x (right) and y (up) around given points."""

    def __init__(self, xy: np.ndarray) -> None:
        lo, hi = xy.min(axis=0) - MARGIN_M, xy.max(axis=0) + MARGIN_M
        self.lo = lo
        w, h = ((hi - lo) * PIXELS_PER_M).astype(int) + 1
        self.image = np.full((h, w, 3), 255, np.uint8)
        self.h = h

    def px(self, xy: np.ndarray) -> np.ndarray:
        p = (np.asarray(xy)[..., :2] - self.lo) * PIXELS_PER_M
        out: np.ndarray = np.rint(np.stack([p[..., 0], self.h - 1 - p[..., 1]], axis=-1))
        return out.astype(np.int32)


def _world_to_colony(tracks: dict[str, Track], root: str) -> np.ndarray | None:
    """Evaluation only: the colony frame is the root's own frame, which began at its first pose."""
    track = tracks.get(root)
    if track is None or not track.truth:
        return None
    world_from_colony = track.truth[0] @ np.linalg.inv(track.estimate[0])
    return np.linalg.inv(world_from_colony)


def draw_colony(
    path: Path,
    fused: MapReply,
    tracks: dict[str, Track],
    colony_tf: dict[str, np.ndarray],
    peer_objects: dict[str, list[dict[str, Any]]],
    own_objects: list[dict[str, Any]],
    *,
    title: str = "",
    colours: dict[str, int] | None = None,
) -> None:
    """The fused occupancy from above (free light, occupied dark), each robot's estimated path
    (solid, in the colony frame) and true path (thin grey-tinted), objects and the CCTV's view."""
    centres = vk.keys_to_centers(fused.keys, fused.resolution)
    occupied = fused.logodds >= 0
    if not len(centres):
        centres = np.zeros((1, 3))
        occupied = np.zeros(1, bool)
    canvas = _Canvas(centres[:, :2])
    img = canvas.image
    # a floor plan: a column is occupied if it has an occupied voxel between 0.15 and 2.0 m
    # (not the floor, not the ceiling), free if it has known voxels only
    body = (centres[:, 2] > 0.15) & (centres[:, 2] < 2.0)
    cell = max(1, round(fused.resolution * PIXELS_PER_M))
    for mask, colour in (
        (np.ones(len(centres), bool), (235, 235, 235)),
        (occupied & body, (40, 40, 40)),
    ):
        px = canvas.px(centres[mask])
        for dx in range(cell):
            for dy in range(cell):
                x = np.clip(px[:, 0] - cell // 2 + dx, 0, img.shape[1] - 1)
                y = np.clip(px[:, 1] - cell // 2 + dy, 0, img.shape[0] - 1)
                img[y, x] = colour
    root = next((a for a, t in colony_tf.items() if np.allclose(t, np.eye(4))), None)
    to_colony = _world_to_colony(tracks, root) if root else None
    legend: list[tuple[str, tuple[int, int, int]]] = []
    for i, (agent, track) in enumerate(tracks.items()):
        colour = _colour((colours or {}).get(agent, i))
        legend.append((f"{agent} ({track.carries})", colour))
        if not track.estimate:
            continue
        if to_colony is not None:
            truth = np.array([to_colony @ t for t in track.truth])[:, :3, 3]
            faint = tuple(int(c + (255 - c) * 0.6) for c in colour)
            cv2.polylines(img, [canvas.px(truth)], False, faint, 1, cv2.LINE_AA)
        tf = colony_tf.get(agent)
        if tf is not None:
            est = np.array([tf @ e for e in track.estimate])[:, :3, 3]
            cv2.polylines(img, [canvas.px(est)], False, colour, 2, cv2.LINE_AA)
            if "CCTV" in track.carries:
                pose = tf @ track.estimate[-1]
                _view(img, canvas, pose, colour)
    for agent, objects in [(fused.agent, own_objects), *peer_objects.items()]:
        tf = colony_tf.get(agent)
        if tf is None:
            continue
        for o in objects:
            p = tf[:3, :3] @ np.asarray(o["position"], float) + tf[:3, 3]
            cv2.circle(img, tuple(int(v) for v in canvas.px(p)), 6, (0, 140, 255), 2, cv2.LINE_AA)
    for j, (text, colour) in enumerate(legend):
        cv2.putText(
            img, text, (10, 20 + 18 * j), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA
        )
    cv2.putText(
        img,
        f"{title + ': ' if title else ''}colony frame: {root or '?'}; "
        "thick: estimate, thin: truth; orange: objects",
        (10, img.shape[0] - 10),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.45,
        (90, 90, 90),
        1,
        cv2.LINE_AA,
    )
    if not cv2.imwrite(str(path), img):
        msg = f"{path}: cannot write the colony picture"
        raise OSError(msg)


def _view(img: np.ndarray, canvas: _Canvas, pose: np.ndarray, colour: tuple[int, int, int]) -> None:
    """A camera's field of view from above: its optical axis (z) projected, +-30 deg, 4 m."""
    axis = pose[:3, 2][:2]
    if np.linalg.norm(axis) < 1e-6:
        return
    heading = np.arctan2(axis[1], axis[0])
    fan = [pose[:2, 3]] + [
        pose[:2, 3] + 4.0 * np.array([np.cos(a), np.sin(a)])
        for a in np.linspace(heading - 0.52, heading + 0.52, 9)
    ]
    cv2.polylines(img, [canvas.px(np.array(fan))], True, colour, 1, cv2.LINE_AA)


@dataclass(frozen=True)
class Series:
    """One line of an error plot: (t, error) points, a mark where it first aligned."""

    label: str
    points: list[tuple[float, float]]
    mark: float | None = None
    colour: int = 0  # index into COLOURS


@dataclass(frozen=True)
class Panel:
    """One plot of an error figure: its title and lines."""

    title: str
    series: list[Series]


def track_series(tracks: dict[str, Track]) -> list[Series]:
    """The daemons' own pose errors over time, one line per member (the demo's plot)."""
    return [
        Series(agent, list(track.errors), track.aligned_at, i)
        for i, (agent, track) in enumerate(tracks.items())
    ]


def draw_errors(
    path: Path, panels: list[Panel], *, note: str = "vertical: first aligned", axis: str = "run"
) -> None:
    """Pose error over time (evaluation), one panel above the other, a vertical tick where each
    line first aligned with a peer; every panel has the same time axis (`axis` names it)."""
    w, h, pad = 800, 340, 50
    lines = [s for p in panels for s in p.series if s.points]
    t_max = max((max(t for t, _ in s.points) for s in lines), default=1.0) or 1.0
    image = np.full((h * max(1, len(panels)), w, 3), 255, np.uint8)
    for k, panel in enumerate(panels):
        img = image[k * h : (k + 1) * h]
        drawn = [s for s in panel.series if s.points]
        e_max = max((max(e for _, e in s.points) for s in drawn), default=0.1) * 1.1 or 0.1
        cv2.rectangle(img, (pad, pad), (w - pad, h - pad), (180, 180, 180), 1)

        def px(t: float, e: float, e_max: float = e_max) -> tuple[int, int]:
            return (int(pad + (w - 2 * pad) * t / t_max), int(h - pad - (h - 2 * pad) * e / e_max))

        for i, s in enumerate(panel.series):
            colour = _colour(s.colour)
            if s.points:
                pts = np.array([px(t, e) for t, e in s.points], np.int32)
                cv2.polylines(img, [pts], False, colour, 2, cv2.LINE_AA)
            if s.mark is not None:
                x = px(s.mark, 0.0)[0]
                cv2.line(img, (x, pad), (x, h - pad), colour, 1, cv2.LINE_AA)
            _text(img, s.label, (pad + 10, pad + 18 * (i + 1)), colour)
        _text(
            img,
            f"{panel.title}: error (m, 0-{e_max:.3f}) over {axis} time (0-{t_max:.0f} s); {note}",
            (pad, pad - 15),
            (60, 60, 60),
        )
    if not cv2.imwrite(str(path), image):
        msg = f"{path}: cannot write the pose-error plot"
        raise OSError(msg)


def _text(img: np.ndarray, text: str, at: tuple[int, int], colour: tuple[int, int, int]) -> None:
    cv2.putText(img, text, at, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
