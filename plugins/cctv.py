"""CCTV adapter: a fixed camera with a known site pose that detects ArUco-tagged objects."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from plugins.checks import as_array, as_pose, camera_intrinsics
from plugins.depth import DepthCamera, DepthFrame
from plugins.errors import SensorInputError
from plugins.observation import AGENT_LABEL, ObjectDetection, Observation
from voxel.sensor import SensorModel

#: A robot's board whose solved normal leaves the horizontal by more than 10 degrees is an
#: ambiguous (flipped) pose solution of a small marker, and dropped.
VERTICAL_SIN = 0.17
#: How well a marker's apparent side is known (pixels, one standard deviation): a marker's
#: solved range is its side's length in the image, so its range is off by range x CORNER_PX /
#: side. Measured with corners refined by `refine_corners` (`python -m
#: colonyd.bench.fix_calibration`, docs/BENCHMARKS.md "The CCTV's claimed covariances"): the
#: range PnP solves, in pixels of the side, is off by RMS 0.22 px over 199 of the sim's 0.24 m
#: robot boards seen by cctv-1 at 8-40 px sides (0.13-0.17 px below 18 px, 0.25-0.30 above;
#: mean -0.1) and by RMS 0.22 px over its 10 landmark markers (0.3 m, office and hall, 9-32 px:
#: -0.50 to +0.26 px). A fixed camera makes its marker's error in every frame (the sim's image
#: has no noise: every frame is the same), so this is one error its sightings share, not noise
#: they average: `OwnObjects` keeps it in the published covariance however many sightings.
#: Before (until 2026-12): 0.5, the largest residual, twice the RMS.
CORNER_PX = 0.25
#: How well the apparent side of a marker whose corners are the detector's is known (pixels):
#: where `edge_corners` cannot fit its edges (`refine_corners` falls back), OpenCV's refined
#: corners lie 0.15-0.3 px inside the square on each axis, its side short by 0.18-0.62 px on the
#: sim CCTV's renders of a 0.3 m marker at 3-15 m (36 views; range error x side up to 0.56 px;
#: docs/BENCHMARKS.md "The CCTV's marker corners") and by 0.3-0.9 px on cctv-1's landmarks before
#: the refinement; the largest, rounded up, is claimed (a bias, not a scatter).
FALLBACK_CORNER_PX = 1.0
#: Where along a side its edge is sampled (fractions of the side, clear of the corners) and the
#: step (pixels) of the samples across it (`refine_corners`).
EDGE_ALONG = np.linspace(0.2, 0.8, 9)
EDGE_STEP = 0.1
#: The widest (pixels, one standard deviation about its centroid) an edge's fall across a side
#: may be at any of its samples: one blurred edge's is narrow (0.29 px for a hard step sampled
#: bilinearly; the sim's renders 0.38-0.75 px over 175 markers and boards at 3-15 m), a sample
#: window holding two falls (the square's edge and clutter's, e.g. a dark band 1-5 px outside a
#: side) is as wide as half their distance or more (1.2-4 px measured). A wider one is a fit to
#: the wrong edge: the detector's corners are kept (`edge_corners` returns None; docs/BENCHMARKS.md
#: "Clutter beside a marker").
EDGE_SPREAD_PX = 1.0
#: The smallest standard deviation (m) of a solved marker's position, along and across the ray.
MARKER_FLOOR_M = 0.01


@dataclass(frozen=True)
class CctvFrame:
    """One CCTV image (H, W, 3) BGR or (H, W) grey uint8, optionally with a registered depth
    image."""

    image: np.ndarray
    depth: np.ndarray | None = None


def marker_corners(length: float) -> np.ndarray:
    """A square marker's corners (4, 3) in its own frame (x right, y up, z out), OpenCV's order."""
    h = length / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def refine_corners(grey: np.ndarray, quad: np.ndarray, cells: int) -> tuple[np.ndarray, float]:
    """A detected marker's corners (4, 2) and how well its apparent side is known (pixels, one
    standard deviation: `marker_covariance`'s `corner_px`): `edge_corners` and `CORNER_PX`, or
    the detector's corners `quad` and `FALLBACK_CORNER_PX` where its lines cannot be fitted."""
    edges = edge_corners(grey, quad, cells)
    if edges is None:
        return np.asarray(quad, np.float64).reshape(4, 2), FALLBACK_CORNER_PX
    return edges, CORNER_PX


def edge_corners(grey: np.ndarray, quad: np.ndarray, cells: int) -> np.ndarray | None:
    """A detected marker's corners (4, 2) moved onto its black square's edges: each side's edge
    is located across the side at EDGE_ALONG by the centroid of the intensity's fall (bright
    outside to dark inside, bilinear samples EDGE_STEP apart, from 0.75 of a cell outside to
    half a cell inside: clear of the next edge in), a line is fitted through them and the corners
    are the lines' crossings. `cells` is the marker's side in cells (bits and border).

    OpenCV's corner refinement (cornerSubPix, half-window 0.3 cell: 3 x 3 px below 30 px
    sides) puts every corner 0.15-0.3 px (each axis) inside the square at 9-45 px sides, on an
    exactly area-sampled image too (at a blurred convex corner the gradient turns along the
    diagonal inside the true corner), so the side is short and the range solved by PnP 0.5-5 %
    long; these edges' centroids are exact to 0.01 px at 20-45 px sides on such an image, to
    0.1 px at 12 px; below ~12 px the border cell is under 2 px wide, its two edges blur
    together and the side comes out up to 0.4 px long (docs/BENCHMARKS.md "The CCTV's marker
    corners"). The sides are taken as straight (no lens distortion). None where a line cannot
    be fitted, a sample's fall is wider than `EDGE_SPREAD_PX` (two edges in its window: the
    square's and clutter's) or a corner would move more than 1 px + a quarter cell
    (`refine_corners` then keeps the detector's)."""
    q = np.asarray(quad, np.float64).reshape(4, 2)
    side = np.roll(q, -1, axis=0) - q  # side i runs from corner i to corner i + 1
    length = np.linalg.norm(side, axis=1)
    if length.min() < 1.0:
        return None
    tangent = side / length[:, None]
    normal = tangent[:, ::-1] * [1.0, -1.0]
    mid = q + 0.5 * side
    normal *= np.sign(np.einsum("ij,ij->i", q.mean(axis=0) - mid, normal))[:, None]  # inward
    cell = float(length.mean()) / cells
    across = np.arange(-max(0.75 * cell, 1.0), max(0.5 * cell, 0.75) + 1e-9, EDGE_STEP)
    base = q[:, None, :] + EDGE_ALONG[None, :, None] * side[:, None, :]  # (4, A, 2)
    points = base[:, :, None, :] + across[None, None, :, None] * normal[:, None, None, :]
    # one row per sample line: cv2.remap takes maps under 32767 columns (a marker hundreds of
    # pixels wide sampled in one row would exceed it)
    xy = points.reshape(-1, len(across), 2).astype(np.float32)
    profile = cv2.remap(
        grey.astype(np.float32), xy[..., 0], xy[..., 1], cv2.INTER_LINEAR, borderValue=0
    ).reshape(points.shape[:3])
    fall = np.clip(profile[:, :, :-1] - profile[:, :, 1:], 0.0, None)  # bright to dark inward
    weight = fall.sum(axis=2)
    if np.any(weight <= 1e-6):
        return None
    at = 0.5 * (across[:-1] + across[1:])
    offset = (fall @ at) / weight  # (4, A)
    if np.any((fall @ at**2) / weight - offset**2 > EDGE_SPREAD_PX**2):
        return None  # a sample's fall is two edges' (the square's and clutter's)
    edge = base + offset[..., None] * normal[:, None, :]
    centre = edge.mean(axis=1)
    _, _, vt = np.linalg.svd(edge - centre[:, None, :])
    direction = vt[:, 0, :]  # (4, 2): each side's fitted line through its centre
    before = np.roll(np.arange(4), 1)  # corner i is where side i - 1 meets side i
    system = np.stack([direction[before], -direction], axis=2)  # (4, 2, 2)
    if np.any(np.abs(np.linalg.det(system)) < 1e-6):
        return None
    steps = np.linalg.solve(system, (centre - centre[before])[..., None])[..., 0]
    refined: np.ndarray = centre[before] + steps[:, :1] * direction[before]
    if np.any(np.linalg.norm(refined - q, axis=1) > 1.0 + 0.25 * cell):
        return None  # a line pulled off the square (another edge, clutter)
    return refined


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """The predefined ArUco dictionary `name` (e.g. "DICT_4X4_50")."""
    code = getattr(cv2.aruco, name, None)
    if not isinstance(code, int) or not name.startswith("DICT_"):
        msg = f"dictionary: expected an ArUco dictionary name like 'DICT_4X4_50', found {name!r}"
        raise SensorInputError(msg)
    return cv2.aruco.getPredefinedDictionary(code)


def marker_covariance(
    position: np.ndarray, side_px: float, corner_px: float = CORNER_PX
) -> np.ndarray:
    """The covariance (3x3, camera frame) of a marker's solved centre `position` from its side
    `side_px` pixels long in the image: along the ray, range x `corner_px` / side (its range
    follows from its apparent size; FALLBACK_CORNER_PX for the detector's own corners); across
    it, MARKER_FLOOR_M (its direction is its pixel)."""
    p = np.asarray(position, np.float64)
    r = float(np.linalg.norm(p))
    across = MARKER_FLOOR_M**2
    if r < 1e-9:
        return np.eye(3) * across
    ray = p / r
    along = max(r * corner_px / max(side_px, 1.0), MARKER_FLOOR_M) ** 2
    return across * np.eye(3) + (along - across) * np.outer(ray, ray)


def confidence(side_px: float, error_px: float) -> float:
    """Detection confidence from the marker's shortest side and reprojection error, in pixels.

    Small markers give poor poses (corner noise is a larger share of the side), so confidence
    grows with the apparent size up to 60 px and falls with the reprojection error.
    """
    return float(np.clip(min(side_px / 60.0, 1.0) * (1.0 - error_px / 10.0), 0.05, 0.99))


class CctvCamera:
    """Fixed pinhole camera; reports ArUco markers as objects and maps its view when given depth."""

    name = "cctv"
    kind = "cctv"

    def __init__(
        self,
        *,
        pose: np.ndarray | None = None,
        K: np.ndarray | None = None,
        fov: float | None = None,
        width: int = 640,
        height: int = 480,
        distortion: np.ndarray | None = None,
        dictionary: str = "DICT_4X4_50",
        marker_length: float = 0.2,
        marker_classes: dict[int, int] | None = None,
        default_class: int = 0,
        depth_scale: float = 0.001,
        max_range: float = 10.0,
        reliability: float = 1.0,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        noise: float = 0.0,
        agent_markers: dict[int, tuple[str, np.ndarray, float]] | None = None,
    ) -> None:
        self.K = camera_intrinsics(K, fov, width, height, "cctv camera")
        #: Markers on other agents: marker id -> (agent id, marker-to-body transform, side length).
        self.agent_markers = {
            int(k): (str(name), as_pose(mount, f"agent_markers[{k}]"), float(length))
            for k, (name, mount, length) in (agent_markers or {}).items()
        }
        self.pose = np.eye(4) if pose is None else as_pose(pose, "pose")
        self.distortion = np.zeros(5) if distortion is None else np.asarray(distortion, np.float64)
        if marker_length <= 0:
            msg = f"marker_length: expected a positive length in metres, found {marker_length!r}"
            raise SensorInputError(msg)
        self.marker_length = float(marker_length)
        self.marker_classes = dict(marker_classes or {})
        self.default_class = int(default_class)
        parameters = cv2.aruco.DetectorParameters()
        parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        aruco = aruco_dictionary(dictionary)
        self.detector = cv2.aruco.ArucoDetector(aruco, parameters)
        #: A marker's side in cells: its bits and its black border (`refine_corners`).
        self.cells = int(aruco.markerSize) + 2 * int(parameters.markerBorderBits)
        self.reliability = float(reliability)
        self.noise = float(noise)
        self.sensor_model = SensorModel(
            prob_hit=prob_hit, prob_miss=prob_miss, max_range=max_range, kind="cctv"
        )
        self.camera = DepthCamera(K=self.K, depth_scale=depth_scale, max_range=max_range)

    def detect(self, image: np.ndarray) -> list[ObjectDetection]:
        """ArUco markers in `image` with their pose in the camera frame (solvePnP, IPPE square)."""
        image = np.asarray(image)
        if (
            image.dtype != np.uint8
            or image.ndim not in (2, 3)
            or (image.ndim == 3 and image.shape[2] not in (1, 3))
        ):
            msg = (
                "image: expected (H, W) or (H, W, 3) uint8, "
                f"found shape {image.shape} dtype {image.dtype}"
            )
            raise SensorInputError(msg)
        grey = (
            image
            if image.ndim == 2
            else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            if image.shape[2] == 3
            else image[:, :, 0]
        )
        corners, ids, _ = self.detector.detectMarkers(grey)
        if ids is None:
            return []
        found = []
        for detected, marker in zip(corners, ids.reshape(-1), strict=True):
            on_agent = self.agent_markers.get(int(marker))
            model = marker_corners(self.marker_length if on_agent is None else on_agent[2])
            quad, corner_px = refine_corners(grey, detected.reshape(4, 2), self.cells)
            ok, rvec, tvec = cv2.solvePnP(
                model, quad, self.K, self.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
            if ok and not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
                # IPPE_SQUARE returns NaN for an exactly square, fronto-parallel quad (refined
                # corners of a rendered marker): the general planar IPPE solves it
                ok, rvec, tvec = cv2.solvePnP(
                    model, quad, self.K, self.distortion, flags=cv2.SOLVEPNP_IPPE
                )
            if not ok or not (np.isfinite(rvec).all() and np.isfinite(tvec).all()):
                continue
            projected, _ = cv2.projectPoints(model, rvec, tvec, self.K, self.distortion)
            error = float(np.linalg.norm(projected.reshape(4, 2) - quad, axis=1).mean())
            sides = np.linalg.norm(np.roll(quad, 1, axis=0) - quad, axis=1)
            side = float(sides.min())
            pose = np.eye(4)
            pose[:3, :3] = cv2.Rodrigues(rvec)[0]
            pose[:3, 3] = tvec.reshape(3)
            label = f"aruco:{int(marker)}"
            covariance: np.ndarray | None = None  # a robot's body pose: its fix carries its own
            if on_agent is not None:  # the agent's body pose in the camera frame
                if abs((self.pose[:3, :3] @ pose[:3, 2])[2]) > VERTICAL_SIN:
                    continue  # boards on robots are vertical: a tilted solution is a flip
                pose = self._at_board_height(pose, float(on_agent[1][2, 3]))
                pose = pose @ np.linalg.inv(on_agent[1])
                label = f"{AGENT_LABEL}{on_agent[0]}"
            else:
                covariance = marker_covariance(pose[:3, 3], float(sides.mean()), corner_px)
            found.append(
                ObjectDetection(
                    object_id=int(marker),
                    class_id=self.marker_classes.get(int(marker), self.default_class),
                    pose=pose,
                    probability=confidence(side, error),
                    label=label,
                    corners=quad,
                    covariance=covariance,
                )
            )
        return found

    def board_incidence(self, detection: ObjectDetection) -> float:
        """The angle (radians, 0-pi/2) between the solved normal of the board an agent's
        detection was solved from and the camera's ray to it: 0 seen square on, pi/2 edge-on
        (`colonyd.fixes.fix_covariance`'s "angle" model). Raises for a detection of no agent's
        board."""
        found = self.agent_markers.get(detection.object_id)
        if found is None or not detection.label.startswith(AGENT_LABEL):
            msg = (
                f"detection: expected an agent's board (one of {sorted(self.agent_markers)}), "
                f"found marker {detection.object_id} labelled {detection.label!r}"
            )
            raise SensorInputError(msg)
        board = detection.pose @ found[1]
        ray = board[:3, 3] / max(float(np.linalg.norm(board[:3, 3])), 1e-9)
        return float(np.arccos(np.clip(abs(float(board[:3, 2] @ ray)), 0.0, 1.0)))

    def _at_board_height(self, marker: np.ndarray, height: float) -> np.ndarray:
        """A robot's board pose (camera frame) moved along the camera's ray through its centre to
        the board's known height above the floor (z = 0 of the camera's surveyed frame): range is
        what a small marker's pose gets worst, the ray's direction what it gets best."""
        o = self.pose[:3, 3]
        c = self.pose[:3, :3] @ marker[:3, 3] + o
        if abs(c[2] - o[2]) < 1e-3:
            return marker  # a ray parallel to the floor: no better range from the height
        scale = (height - o[2]) / (c[2] - o[2])
        if not 0.5 < scale < 2.0:
            return marker
        out = marker.copy()
        out[:3, 3] = marker[:3, 3] * scale
        return out

    def observe(
        self,
        reading: CctvFrame | np.ndarray,
        *,
        pose: np.ndarray | None = None,
        time: float = 0.0,
        odometry: np.ndarray | None = None,
        frame: str = "",
    ) -> Observation:
        """Objects seen in the image; with depth, also the view's points coloured and labelled by
        marker."""
        if not isinstance(reading, CctvFrame):
            reading = CctvFrame(image=reading)
        objects = tuple(self.detect(reading.image))
        camera_pose = self.pose if pose is None else as_pose(pose, "pose")
        if reading.depth is None:
            return Observation(
                sensor=self.name,
                time=time,
                points=np.empty((0, 3)),
                pose=camera_pose,
                objects=objects,
                odometry=odometry,
                frame=frame,
            )
        depth = np.asarray(reading.depth)
        image = np.asarray(reading.image)
        if depth.shape != image.shape[:2]:
            msg = f"depth: expected the image's shape {image.shape[:2]}, found {depth.shape}"
            raise SensorInputError(msg)
        labels = np.full(depth.shape, -1, np.int32)
        probs = np.zeros(depth.shape, np.float32)
        for obj in objects:
            if obj.label.startswith(AGENT_LABEL):
                continue  # a robot passing by: not part of the map
            assert obj.corners is not None  # detect() gives every marker its image corners
            quad = np.round(obj.corners).astype(np.int32)
            cv2.fillConvexPoly(labels, quad, obj.class_id)
            cv2.fillConvexPoly(probs, quad, obj.probability)
        colour = image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)
        frame_in = DepthFrame(
            depth=depth,
            colour=as_array(colour, "image", shape=(*depth.shape, 3), dtype=np.uint8),
            labels=labels,
            label_probs=probs,
        )
        view = self.camera.observe(
            frame_in, pose=camera_pose, time=time, odometry=odometry, frame=frame
        )
        return Observation(
            sensor=self.name,
            time=time,
            points=view.points,
            pose=camera_pose,
            colours=view.colours,
            class_ids=view.class_ids,
            class_probs=view.class_probs,
            objects=objects,
            depth=view.depth,
            odometry=odometry,
            frame=frame,
        )
