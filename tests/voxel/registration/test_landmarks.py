"""Objects as alignment evidence: class-consistent RANSAC; objects settle what geometry cannot."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from voxel.errors import AlignmentError
from voxel.registration import AlignParams, Landmarks, MapCloud, align_clouds, match_landmarks
from voxel.registration.transform import apply, rigid


def _scene(seed: int = 0) -> Landmarks:
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-6, 6, 7), rng.uniform(-4, 4, 7), rng.uniform(0.2, 1.0, 7)])
    return Landmarks(pos, np.array([3, 3, 4, 4, 5, 5, 5]))


def _moved(objs: Landmarks, t: np.ndarray, noise: float, seed: int = 1) -> Landmarks:
    rng = np.random.default_rng(seed)
    pos = apply(t, objs.positions) + rng.normal(scale=noise, size=objs.positions.shape)
    return Landmarks(pos, objs.classes.copy())


@pytest.mark.parametrize("dof", [4, 6])
def test_objects_fit_recovers_the_pose_despite_a_wrong_object(dof: int) -> None:
    a = _scene()
    move = rigid(3.0, -2.0, 0.4, yaw=math.radians(123.0))  # a's frame into b's
    b = _moved(a, move, 0.05)
    b.positions[0] += (2.5, 0.0, 0.0)  # one object moved (a wrong match if associated)
    fit = match_landmarks(a, b, dof)
    assert fit.found, fit.reason
    truth = np.linalg.inv(move)
    err = apply(fit.transform, b.positions[1:]) - apply(truth, b.positions[1:])
    assert np.max(np.linalg.norm(err, axis=1)) < 0.2
    assert fit.inliers == 6 and 0 not in fit.pairs[:, 0]
    assert fit.ambiguity <= 0.5


def test_objects_fit_refuses_too_few_and_reports_symmetry() -> None:
    a = Landmarks(np.array([[0.0, 0.0, 0.5], [4.0, 0.0, 0.5]]), np.array([5, 5]))
    one = match_landmarks(a, Landmarks(a.positions[:1], a.classes[:1]))
    assert not one.found and "expected at least 2" in (one.reason or "")
    other_class = match_landmarks(a, Landmarks(a.positions, np.array([3, 4])))
    assert not other_class.found and "shared class" in (other_class.reason or "")
    symmetric = match_landmarks(a, _moved(a, rigid(1.0, 2.0, yaw=0.3), 0.0))
    assert symmetric.found and symmetric.ambiguity == 1.0  # turned round it fits as well
    six = match_landmarks(a, a, 6)
    assert not six.found and "at least 3" in (six.reason or "")


# The sim office: two rooms of one shape, so geometry alone cannot tell them apart; a depth
# camera's objects (class-labelled) can, against a 3D LiDAR's map that has no classes.
# depth-1's first 20 s (200 frames) take in both rooms; lidar3d-1's first 3 s (30 frames) the
# west room alone, which fits either room of depth-1's map by geometry.
Mapped = tuple[MapCloud, Landmarks, np.ndarray]


@pytest.fixture(scope="module")
def office() -> Callable[[str, str, int], Mapped]:
    """The map, objects and true start pose of (world, agent, frames), each built once and only
    when a test asks for it (xdist may spread this module's tests over workers)."""
    built: dict[tuple[str, str, int], Mapped] = {}

    def get(world: str, agent: str, frames: int = 120) -> Mapped:
        if (world, agent, frames) not in built:
            built[world, agent, frames] = _mapped(world, agent, frames)
        return built[world, agent, frames]

    return get


def _mapped(world: str, agent: str, frames: int) -> Mapped:
    from colonyd.bench.regspeed import sim_map
    from plugins.checks import pose_matrix
    from plugins.sim import AGENTS, Path

    cloud, objects = sim_map(world, agent, frames)
    s = AGENTS[world][agent]
    x, y, yaw = Path(s.waypoints, s.speed, s.turn_rate)(0.0)  # evaluation only
    return cloud, objects, pose_matrix(x, y, 0.0, yaw)


def _error(found: np.ndarray, a_start: np.ndarray, b_start: np.ndarray) -> tuple[float, float]:
    e = np.linalg.inv(np.linalg.inv(a_start) @ b_start) @ found
    return float(np.linalg.norm(e[:3, 3])), abs(math.degrees(math.atan2(e[1, 0], e[0, 0])))


def test_objects_settle_the_symmetric_office_and_geometry_alone_refuses(office) -> None:
    a, oa, sa = office("office", "depth-1", 200)
    b, ob, sb = office("office", "lidar3d-1", 30)
    alone = align_clouds(a, b, AlignParams(dof=4))
    assert not alone.aligned and "ambiguous" in (alone.reason or "")
    both = align_clouds(a, b, AlignParams(dof=4), objects_a=oa, objects_b=ob)
    assert both.aligned, both.reason
    t_err, yaw_err = _error(both.transform, sa, sb)
    assert t_err < 0.1 and yaw_err < 2.0
    assert both.objects is not None and both.objects["supported"] >= 2
    assert both.objects["contradicted"] == 0 and both.objects["poses_ruled_out"] >= 1
    assert both.geometric_ambiguity > 0.5 >= both.ambiguity and "objects" in both.method


def test_a_2d_scan_aligns_to_the_slice_of_a_3d_map(office) -> None:
    a, _, sa = office("office", "lidar3d-1")
    b, _, sb = office("office", "lidar-1")
    assert b.planar and not a.planar
    result = align_clouds(a, b, AlignParams(dof=4))
    assert result.aligned, result.reason
    assert result.method.startswith("slice+") and result.dof == 3
    t_err, yaw_err = _error(result.transform, sa, sb)
    assert t_err < 0.1 and yaw_err < 2.0


def test_objects_in_the_other_maps_open_space_refuse_a_foreign_map(office) -> None:
    a, oa, _ = office("office", "lidar3d-1")
    b, ob, _ = office("room", "depth-1")  # the room fits one office room by geometry
    result = align_clouds(a, b, AlignParams(dof=4), objects_a=oa, objects_b=ob)
    assert not result.aligned
    assert result.objects is not None and result.objects["contradicted"] >= 1


# A 9 x 5 m room with furniture in its west half, seen by A only as far as x = 4.6 m (a short-
# range scanner: every wall, but open space and furniture only in the west); B is the same map
# moved. Turned 180 degrees B fits the walls nearly as well, and its objects then fall in A's
# unseen east half, where nothing rules them out.
FURNITURE = ((1.5, 1.5), (2.5, 3.5), (3.8, 1.2), (1.2, 3.8), (4.0, 3.0))
MOVE = rigid(1.3, -0.7, 0.0, yaw=math.radians(37.0))


def _room(furniture: tuple[tuple[float, float], ...], seen_x: float) -> tuple[MapCloud, MapCloud]:
    """A (planar, open space known for x < seen_x) and B (A moved by MOVE)."""
    from tests.voxel.registration.worlds import RES, crop_and_move

    occ = np.zeros((90, 50), bool)
    occ[[0, -1], :] = occ[:, [0, -1]] = True
    for x, y in furniture:
        i, j = round(x / RES), round(y / RES)
        occ[i - 2 : i + 2, j - 2 : j + 2] = True
    known = occ.copy()
    known[: round(seen_x / RES), :] = True
    cells = np.argwhere(known)
    keys = np.column_stack([cells, np.zeros(len(cells), np.int64)])
    mask = occ[cells[:, 0], cells[:, 1]]
    return crop_and_move(keys, mask, -1.0, 99.0), crop_and_move(keys, mask, -1.0, 99.0, MOVE)


def _objects(where: tuple[tuple[float, float], ...]) -> Landmarks:
    """Objects (class 5) at `where` in A's frame, as B sees them (in B's frame)."""
    return Landmarks.of([(5, apply(MOVE, np.array([[x, y, 0.5]]))[0]) for x, y in where])


def test_objects_on_surfaces_outvote_rivals_whose_objects_fall_unobserved() -> None:
    a, b = _room(FURNITURE, 4.6)
    ob = _objects(FURNITURE)
    off = align_clouds(a, b, AlignParams(dof=4, prefer_backed=None), objects_b=ob)
    assert not off.aligned and "ambiguous" in (off.reason or "")  # main's rule
    result = align_clouds(a, b, AlignParams(dof=4), objects_b=ob)
    assert result.aligned, result.reason
    t_err, yaw_err = _error(result.transform, np.eye(4), np.linalg.inv(MOVE))
    assert t_err < 0.05 and yaw_err < 1.0
    assert result.objects is not None and result.objects["supported"] == 5
    assert result.objects["poses_unbacked"] >= 1
    assert result.geometric_ambiguity > 0.5 >= result.ambiguity


@pytest.mark.parametrize("case", ["too few", "contradicted", "rival backed too"])
def test_unobserved_rivals_stay_when_objects_are_few_contradicted_or_back_them_too(
    case: str,
) -> None:
    """Too few objects (3 of the 4 needed) back the pose; objects land in A's open space at the
    geometry's best pose (which they rule out: the rival left has none on surfaces); alike
    halves (a room symmetric under a half turn, seen whole) back the turned pose as well."""
    mirrored = tuple((9.0 - x, 5.0 - y) for x, y in FURNITURE)
    furniture, seen_x, where = {
        "too few": (FURNITURE, 4.6, FURNITURE[:3]),
        "contradicted": (FURNITURE, 4.6, (*FURNITURE, (2.0, 2.5), (3.2, 2.4), (1.0, 2.6))),
        "rival backed too": (FURNITURE + mirrored, 9.0, FURNITURE + mirrored),
    }[case]
    a, b = _room(furniture, seen_x)
    result = align_clouds(a, b, AlignParams(dof=4), objects_b=_objects(where))
    assert not result.aligned
    assert result.objects is not None and result.objects["poses_unbacked"] == 0
    if case == "contradicted":
        assert result.objects["contradicted"] >= 2 and "objects" in result.failed_checks
    else:
        assert "ambiguous" in (result.reason or "")


def test_prefer_backed_below_two_objects_is_refused() -> None:
    a, b = _room(FURNITURE, 4.6)
    with pytest.raises(AlignmentError, match="prefer_backed: expected None"):
        align_clouds(a, b, AlignParams(dof=4, prefer_backed=1))
