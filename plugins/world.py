"""Simulated world: rooms, walls and labelled objects, with a ray caster vectorised over rays."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from plugins.errors import SourceSpecError

#: Class ids of the simulated world's labels (-1 = unlabelled).
CLASSES = {"wall": 1, "floor": 2, "box": 3, "cylinder": 4, "landmark": 5}

_EPS = 1e-9


@dataclass(frozen=True)
class Box:
    """Axis-aligned solid box."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    class_id: int
    object_id: int = -1
    colour: tuple[int, int, int] = (180, 180, 180)  # BGR


@dataclass(frozen=True)
class Cylinder:
    """Vertical solid cylinder."""

    centre: tuple[float, float]
    radius: float
    z0: float
    z1: float
    class_id: int
    object_id: int = -1
    colour: tuple[int, int, int] = (60, 120, 200)


@dataclass(frozen=True)
class Marker:
    """An ArUco marker printed on a vertical box face: black square of side `length` on a white
    tag."""

    marker_id: int
    centre: tuple[float, float, float]
    normal: tuple[float, float, float]  # horizontal, pointing out of the face
    length: float
    object_id: int = -1
    margin: float = 0.25  # white border around the marker, as a fraction of its length

    def frame(self) -> np.ndarray:
        """Marker-to-world transform (x right, y up, z out of the face), OpenCV's marker frame."""
        z = np.asarray(self.normal, np.float64)
        z = z / np.linalg.norm(z)
        y = np.array([0.0, 0.0, 1.0])
        x = np.cross(y, z)
        pose = np.eye(4)
        pose[:3, :3] = np.column_stack([x, y, z])
        pose[:3, 3] = self.centre
        return pose


@dataclass(frozen=True)
class Hits:
    """Result of casting M rays: distance along each (unnormalised) direction, inf = no hit."""

    t: np.ndarray  # (M,)
    normal: np.ndarray  # (M, 3) world frame, facing the ray
    class_id: np.ndarray  # (M,) int32, -1 = none
    object_id: np.ndarray  # (M,) int32
    colour: np.ndarray  # (M, 3) uint8 BGR


@dataclass
class World:
    """A static scene: boxes, vertical cylinders, a floor plane and ArUco markers on box faces."""

    name: str
    boxes: list[Box] = field(default_factory=list)
    cylinders: list[Cylinder] = field(default_factory=list)
    markers: list[Marker] = field(default_factory=list)
    floor: float | None = 0.0
    floor_colour: tuple[int, int, int] = (90, 110, 90)
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        self._lo = np.array([b.lo for b in self.boxes], np.float64).reshape(-1, 3)
        self._hi = np.array([b.hi for b in self.boxes], np.float64).reshape(-1, 3)
        self._box_cls = np.array([b.class_id for b in self.boxes], np.int32)
        self._box_obj = np.array([b.object_id for b in self.boxes], np.int32)
        self._box_col = np.array([b.colour for b in self.boxes], np.uint8).reshape(-1, 3)
        self._bitmaps: dict[int, np.ndarray] = {}

    # ground truth ---------------------------------------------------------------------------
    def objects(self) -> dict[int, tuple[int, np.ndarray]]:
        """Labelled objects: object id -> (class id, centre (3,))."""
        out: dict[int, tuple[int, np.ndarray]] = {}
        for b in self.boxes:
            if b.object_id >= 0:
                out[b.object_id] = (b.class_id, (np.asarray(b.lo) + np.asarray(b.hi)) / 2)
        for c in self.cylinders:
            if c.object_id >= 0:
                out[c.object_id] = (c.class_id, np.array([*c.centre, (c.z0 + c.z1) / 2]))
        return out

    def surface_points(self, spacing: float = 0.02) -> np.ndarray:
        """Points (N, 3) every `spacing` m on every surface: box faces, cylinder sides and tops,
        and the floor under the boxes' extent. Ground truth, for evaluating maps only."""
        parts = []

        def grid(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
            axes = [np.arange(lo[i], hi[i] + spacing / 2, spacing) for i in range(3)]
            return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

        for lo, hi in zip(self._lo, self._hi, strict=True):
            for axis in range(3):
                for side in (lo[axis], hi[axis]):
                    a, b = lo.copy(), hi.copy()
                    a[axis] = b[axis] = side
                    parts.append(grid(a, b))
        for c in self.cylinders:
            n = max(8, int(2 * np.pi * c.radius / spacing))
            ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
            z = np.arange(c.z0, c.z1 + spacing / 2, spacing)
            ring = np.column_stack([c.radius * np.cos(ang), c.radius * np.sin(ang)])
            side = np.column_stack([np.repeat(ring + c.centre, len(z), axis=0), np.tile(z, n)])
            r = np.arange(0.0, c.radius, spacing)
            disc = (
                np.column_stack(
                    [np.outer(r, np.cos(ang)).ravel(), np.outer(r, np.sin(ang)).ravel()]
                )
                + c.centre
            )
            parts += [side, np.column_stack([disc, np.full(len(disc), c.z1)])]
        if self.floor is not None and len(self._lo):
            lo, hi = self._lo.min(axis=0), self._hi.max(axis=0)
            lo[2] = hi[2] = self.floor
            parts.append(grid(lo, hi))
        return np.concatenate(parts) if parts else np.empty((0, 3))

    def marker_objects(self) -> dict[int, int]:
        """Marker id -> object id of the object it is printed on."""
        return {m.marker_id: m.object_id for m in self.markers}

    # ray casting ----------------------------------------------------------------------------
    def cast(self, origin: np.ndarray, directions: np.ndarray, chunk: int = 65536) -> Hits:
        """First hit of rays origin + t * directions (M, 3); all rays at once, in chunks."""
        directions = np.asarray(directions, np.float64).reshape(-1, 3)
        origin = np.asarray(origin, np.float64).reshape(3)
        parts = [
            self._cast(origin, directions[i : i + chunk])
            for i in range(0, max(len(directions), 1), chunk)
        ]
        return Hits(
            *(
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("t", "normal", "class_id", "object_id", "colour")
            )
        )

    def _cast(self, o: np.ndarray, d: np.ndarray) -> Hits:
        m = d.shape[0]
        t = np.full(m, np.inf)
        normal = np.zeros((m, 3))
        cls = np.full(m, -1, np.int32)
        obj = np.full(m, -1, np.int32)
        colour = np.zeros((m, 3), np.uint8)

        def take(
            tc: np.ndarray,
            nc: np.ndarray,
            c: np.ndarray,
            oid: np.ndarray,
            col: np.ndarray,
        ) -> None:
            better = tc < t
            t[better] = tc[better]
            normal[better] = nc[better] if nc.ndim == 2 else nc
            cls[better] = c[better] if np.ndim(c) else c
            obj[better] = oid[better] if np.ndim(oid) else oid
            colour[better] = col[better] if col.ndim == 2 else col

        if self.floor is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                tf = (self.floor - o[2]) / d[:, 2]
            tf = np.where(np.isfinite(tf) & (tf > _EPS), tf, np.inf)
            up = 1.0 if o[2] >= self.floor else -1.0
            take(
                tf,
                np.array([0.0, 0.0, up]),
                np.array(CLASSES["floor"], np.int32),
                np.array(-1, np.int32),
                np.array(self.floor_colour, np.uint8),
            )

        if len(self.boxes):
            safe = np.where(np.abs(d) < 1e-12, 1e-12, d)
            inv = 1.0 / safe  # (M, 3)
            near, far = [], []
            for axis in range(3):  # per axis: (M, B) entry and exit distances of the slabs
                lo = (self._lo[:, axis] - o[axis]) * inv[:, axis, None]
                hi = (self._hi[:, axis] - o[axis]) * inv[:, axis, None]
                near.append(np.minimum(lo, hi))
                far.append(np.maximum(lo, hi))
            tmin = np.maximum(np.maximum(near[0], near[1]), near[2])
            tmax = np.minimum(np.minimum(far[0], far[1]), far[2])
            tb = np.where((tmax >= tmin) & (tmin > _EPS), tmin, np.inf)
            k = tb.argmin(axis=1)  # best box per ray
            rows = np.arange(m)
            tk = tb[rows, k]
            hit_axis = np.where(near[0][rows, k] == tk, 0, np.where(near[1][rows, k] == tk, 1, 2))
            nb = np.zeros((m, 3))
            nb[rows, hit_axis] = -np.sign(d[rows, hit_axis])
            take(tk, nb, self._box_cls[k], self._box_obj[k], self._box_col[k])

        for c in self.cylinders:
            tc, nc = _cylinder(o, d, c)
            take(
                tc,
                nc,
                np.array(c.class_id, np.int32),
                np.array(c.object_id, np.int32),
                np.array(c.colour, np.uint8),
            )
        return Hits(t=t, normal=normal, class_id=cls, object_id=obj, colour=colour)

    # appearance -----------------------------------------------------------------------------
    def render_colour(
        self,
        K: np.ndarray,
        pose: np.ndarray,
        size: tuple[int, int],
        directions: np.ndarray,
        hits: Hits,
        moving: list[Marker] | None = None,
    ) -> np.ndarray:
        """BGR image (H, W, 3) of a pinhole camera's hits: shaded surfaces with markers warped on.

        `directions` are the world-frame rays of the pixels (row-major, as cast). Markers are drawn
        by a perspective warp of their bitmap (sub-pixel edges), only where the cast ray hits the
        marker's face (occlusion). `moving` markers (boards on robots, not part of the cast
        scene) are drawn where they are nearer than the scene.
        """
        h, w = size
        d = np.asarray(directions, np.float64)
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        lit = 0.55 + 0.45 * np.abs(np.einsum("ij,ij->i", unit, hits.normal))
        base = hits.colour.astype(np.float32)
        hit = np.isfinite(hits.t)
        base[~hit] = (200.0, 190.0, 170.0)  # void
        base *= lit[:, None]
        points = pose[:3, 3] + d * np.where(hit, hits.t, 0.0)[:, None]
        world_to_cam = np.linalg.inv(pose)
        for i, marker in enumerate([*self.markers, *(moving or [])]):
            board = i >= len(self.markers)
            frame = marker.frame()
            if (frame[:3, 3] - pose[:3, 3]) @ frame[:3, 2] >= 0:
                continue  # seen from behind
            half = marker.length * (0.5 + marker.margin)
            corners = np.array(
                [[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]]
            )
            cam = (corners @ frame[:3, :3].T + frame[:3, 3]) @ world_to_cam[
                :3, :3
            ].T + world_to_cam[:3, 3]
            if np.any(cam[:, 2] <= 0.05):
                continue
            uv = cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
            lo = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
            hi = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 2, [w, h])
            if np.any(hi <= lo):
                continue
            # pixels of the tag's bounding box whose ray hits the marker's face (occlusion test)
            rows, cols = np.mgrid[lo[1] : hi[1], lo[0] : hi[0]]
            index = (rows * w + cols).reshape(-1)
            if board:  # in front of the scene where the ray meets the board's plane first
                ray = d[index]
                with np.errstate(divide="ignore", invalid="ignore"):
                    t_board = ((frame[:3, 3] - pose[:3, 3]) @ frame[:3, 2]) / (ray @ frame[:3, 2])
                face = (t_board > 0) & (~hit[index] | (t_board < hits.t[index]))
            else:
                local = (points[index] - frame[:3, 3]) @ frame[:3, :3]
                face = (
                    hit[index]
                    & (np.abs(local[:, 2]) < 1e-4)
                    & (hits.normal[index] @ frame[:3, 2] > 0.5)
                )
            if not face.any():
                continue
            tag = self._tag(marker)
            side = float(np.linalg.norm(np.roll(uv, 1, axis=0) - uv, axis=1).max())
            if side < tag.shape[0] / 2:  # pre-filter: anti-aliased edges at the projected size
                tag_px = max(round(side * 2), 8)
                tag = cv2.resize(tag, (tag_px, tag_px), interpolation=cv2.INTER_AREA)
            s = tag.shape[0]
            src = np.array(
                [[-0.5, -0.5], [s - 0.5, -0.5], [s - 0.5, s - 0.5], [-0.5, s - 0.5]], np.float32
            )
            H = cv2.getPerspectiveTransform(src, (uv - lo).astype(np.float32))
            box = (int(hi[0] - lo[0]), int(hi[1] - lo[1]))
            warped = cv2.warpPerspective(tag, H, box, flags=cv2.INTER_AREA, borderValue=0).reshape(
                -1
            )
            cover = cv2.warpPerspective(
                np.full_like(tag, 255), H, box, flags=cv2.INTER_AREA, borderValue=0
            ).reshape(-1)
            alpha = cover.astype(np.float32) / 255.0 * face
            shade = lit[index, None]
            base[index] = (
                base[index] * (1 - alpha[:, None]) + (warped[:, None] * shade) * alpha[:, None]
            )
        return np.clip(base, 0, 255).astype(np.uint8).reshape(h, w, 3)

    def _tag(self, marker: Marker) -> np.ndarray:
        """The marker's printed tag (marker on a white margin), 16 px per marker cell."""
        if marker.marker_id not in self._bitmaps:
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
            cells = dictionary.markerSize + 2
            px = 16
            inner = cv2.aruco.generateImageMarker(
                dictionary, marker.marker_id, cells * px, borderBits=1
            )
            pad = round(marker.margin * cells * px)
            self._bitmaps[marker.marker_id] = cv2.copyMakeBorder(
                inner, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255
            )
        return self._bitmaps[marker.marker_id]


def _cylinder(o: np.ndarray, d: np.ndarray, c: Cylinder) -> tuple[np.ndarray, np.ndarray]:
    """First hit (t, normal) of rays with a capped vertical cylinder."""
    m = d.shape[0]
    ox, oy = o[0] - c.centre[0], o[1] - c.centre[1]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2.0 * (ox * d[:, 0] + oy * d[:, 1])
    cc = ox * ox + oy * oy - c.radius**2
    disc = b * b - 4 * a * cc
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = (-b - np.sqrt(disc)) / (2 * a)
    z = o[2] + ts * d[:, 2]
    side_ok = (disc >= 0) & (a > 1e-18) & (ts > _EPS) & (z >= c.z0) & (z <= c.z1)
    t_side = np.where(side_ok, ts, np.inf)
    n_side = np.zeros((m, 3))
    with np.errstate(invalid="ignore"):
        n_side[:, 0] = (ox + ts * d[:, 0]) / c.radius
        n_side[:, 1] = (oy + ts * d[:, 1]) / c.radius
    cap_z = c.z1 if o[2] > c.z1 else c.z0
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = (cap_z - o[2]) / d[:, 2]
        xc, yc = ox + tc * d[:, 0], oy + tc * d[:, 1]
        cap_ok = (
            np.isfinite(tc)
            & (tc > _EPS)
            & (xc * xc + yc * yc <= c.radius**2)
            & (o[2] > c.z1 or o[2] < c.z0)
        )
    t_cap = np.where(cap_ok, tc, np.inf)
    n_cap = np.zeros((m, 3))
    n_cap[:, 2] = 1.0 if o[2] > c.z1 else -1.0
    use_cap = t_cap < t_side
    return np.where(use_cap, t_cap, t_side), np.where(use_cap[:, None], n_cap, n_side)


# worlds -------------------------------------------------------------------------------------


def _walls(
    x0: float, y0: float, x1: float, y1: float, height: float, thick: float = 0.1
) -> list[Box]:
    """Four walls whose inner faces bound [x0, x1] x [y0, y1]."""
    w, cls, col = thick, CLASSES["wall"], (200, 200, 205)
    return [
        Box((x0 - w, y0 - w, 0.0), (x1 + w, y0, height), cls, colour=col),
        Box((x0 - w, y1, 0.0), (x1 + w, y1 + w, height), cls, colour=col),
        Box((x0 - w, y0, 0.0), (x0, y1, height), cls, colour=col),
        Box((x1, y0, 0.0), (x1 + w, y1, height), cls, colour=col),
    ]


def _landmark(
    object_id: int,
    x: float,
    y: float,
    first_marker: int,
    side: float = 0.5,
    height: float = 1.4,
    length: float = 0.3,
) -> tuple[Box, list[Marker]]:
    """A square pillar with one ArUco marker on each vertical face, at 1.0 m height."""
    h = side / 2
    box = Box(
        (x - h, y - h, 0.0), (x + h, y + h, height), CLASSES["landmark"], object_id, (170, 170, 170)
    )
    faces = [
        ((1, 0, 0), (x + h, y, 1.0)),
        ((-1, 0, 0), (x - h, y, 1.0)),
        ((0, 1, 0), (x, y + h, 1.0)),
        ((0, -1, 0), (x, y - h, 1.0)),
    ]
    markers = [
        Marker(first_marker + i, centre, normal, length, object_id)
        for i, (normal, centre) in enumerate(faces)
    ]
    return box, markers


def room_world() -> World:
    """A 6 x 6 m square room (inner wall faces at x, y = +-3), 2.5 m high, three labelled
    objects."""
    landmark, markers = _landmark(3, 1.5, 1.5, 0)
    return World(
        name="room",
        boxes=[
            *_walls(-3.0, -3.0, 3.0, 3.0, 2.5),
            Box((-2.0, 1.0, 0.0), (-1.4, 1.6, 0.8), CLASSES["box"], 1, (40, 90, 160)),
            landmark,
        ],
        cylinders=[Cylinder((1.5, -1.5), 0.25, 0.0, 1.2, CLASSES["cylinder"], 2)],
        markers=markers,
    )


def office_world() -> World:
    """A 12 x 8 m office: two rooms joined by a 1.2 m doorway, boxes, bins and four tagged
    landmarks."""
    return _office("office", 1.0, divided=True)


#: The hall's scale in plan against the office (docs/LOCALISATION.md "A sparse hall").
HALL_SCALE = 1.5


def hall_world() -> World:
    """An 18 x 12 m hall, the paper's "relatively sparse environment": the office's furniture
    (the same boxes, bins and four tagged landmarks, of the same sizes) with every position
    scaled by HALL_SCALE in plan, and no dividing wall. From most of its floor a 4 m scanner
    sees one or two objects and no wall."""
    return _office("hall", HALL_SCALE, divided=False)


def _office(name: str, scale: float, *, divided: bool) -> World:
    """The office's walls and furniture, positions (not sizes) scaled by `scale` in plan;
    `divided`: with the dividing wall and its doorway."""
    cls, col = CLASSES["wall"], (200, 200, 205)

    def moved(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> tuple[Any, Any]:
        """lo, hi moved so that their centre is scaled in plan (the same box at scale 1)."""
        shift = [(scale - 1.0) * (a + b) / 2 for a, b in zip(lo[:2], hi[:2], strict=True)]
        return (lo[0] + shift[0], lo[1] + shift[1], lo[2]), (
            hi[0] + shift[0],
            hi[1] + shift[1],
            hi[2],
        )

    boxes = _walls(-6.0 * scale, -4.0 * scale, 6.0 * scale, 4.0 * scale, 2.7)
    if divided:
        boxes += [
            Box((-0.05, -4.0, 0.0), (0.05, -0.6, 2.7), cls, colour=col),
            Box((-0.05, 0.6, 0.0), (0.05, 4.0, 2.7), cls, colour=col),
        ]
    for lo, hi, object_id, colour in (
        ((-4.5, 2.5, 0.0), (-3.3, 3.3, 0.75), 1, (40, 90, 160)),
        ((3.0, -3.4, 0.0), (3.8, -2.6, 1.0), 2, (60, 160, 60)),
        ((4.4, 2.2, 0.0), (5.2, 3.0, 0.5), 3, (160, 60, 60)),
    ):
        boxes.append(Box(*moved(lo, hi), CLASSES["box"], object_id, colour))
    markers: list[Marker] = []
    for i, (x, y) in enumerate([(-3.0, -2.0), (-1.5, 1.5), (2.0, 1.0), (4.0, -1.0)]):
        box, ms = _landmark(10 + i, x * scale, y * scale, 4 * i)
        boxes.append(box)
        markers += ms
    cylinders = [
        Cylinder((x * scale, y * scale), r, 0.0, h, CLASSES["cylinder"], object_id)
        for (x, y), r, h, object_id in (
            ((-4.8, -3.2), 0.2, 0.9, 20),
            ((1.2, -2.5), 0.3, 1.1, 21),
            ((5.2, 0.5), 0.25, 1.0, 22),
        )
    ]
    return World(name=name, boxes=boxes, cylinders=cylinders, markers=markers)


def box_room(side: float, height: float = 2.5) -> World:
    """An empty square room without a floor: inner wall faces at 0 and `side` on x and y (the
    synthetic scanner's)."""
    return World(name="box", boxes=_walls(0.0, 0.0, side, side, height), floor=None)


#: Offset of the furnished room's surfaces from voxel boundaries, so float32 (OctoMap) and float64
#: (ours) agree on the keys of its surfaces.
FURNISHED_SHIFT = (0.0131, 0.0217, 0.0093)


def furnished_room(thick: float = 0.1) -> World:
    """An 8 x 6 x 2.8 m closed room (floor and ceiling as boxes) with a table, cupboard, bed, chair
    and wall shelf, unlabelled, shifted by FURNISHED_SHIFT: the benchmarks' scene."""
    shift = np.array(FURNISHED_SHIFT)
    lo, hi = np.array([-4.0, -3.0, 0.0]) + shift, np.array([4.0, 3.0, 2.8]) + shift
    col = (200, 200, 205)
    # Six slabs whose inner faces are the room's faces, overlapping at the edges.
    slabs = []
    for axis in range(3):
        for side in (lo, hi):
            a, b = lo - thick, hi + thick
            a[axis], b[axis] = (
                (side[axis] - thick, side[axis]) if side is lo else (side[axis], side[axis] + thick)
            )
            slabs.append(Box(tuple(a.tolist()), tuple(b.tolist()), CLASSES["wall"], colour=col))
    furniture = [
        ((1.0, -1.0, 0.0), (2.2, 0.2, 0.75)),  # table
        ((-2.5, 1.5, 0.0), (-1.5, 2.9, 1.9)),  # cupboard
        ((2.8, 1.8, 0.0), (3.9, 2.9, 0.5)),  # bed
        ((-0.4, -2.6, 0.0), (0.3, -1.9, 1.1)),  # chair
        ((-3.2, -1.0, 0.8), (-2.9, 0.5, 1.6)),  # shelf on the wall
    ]
    boxes = [
        Box(
            tuple((np.array(a) + shift).tolist()),
            tuple((np.array(b) + shift).tolist()),
            CLASSES["box"],
        )
        for a, b in furniture
    ]
    return World(name="furnished", boxes=[*slabs, *boxes], floor=None)


WORLDS = {"room": room_world, "office": office_world, "hall": hall_world}


def get_world(name: str) -> World:
    """The built-in world called `name`."""
    if name not in WORLDS:
        msg = f"world: expected one of {sorted(WORLDS)}, found {name!r}"
        raise SourceSpecError(msg)
    return WORLDS[name]()
