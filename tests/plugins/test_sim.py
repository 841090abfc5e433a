"""Tests of the simulated source: determinism, odometry noise, ground truth, speed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from plugins.errors import SourceSpecError
from plugins.sim import AGENTS, ROBOT_RADIUS, Path, SimSource, render
from plugins.world import WORLDS, get_world


def test_same_seed_same_stream_other_seed_other_noise() -> None:
    a = list(SimSource(world="room", agent="lidar-1", frames=20, seed=3))
    b = list(SimSource(world="room", agent="lidar-1", frames=20, seed=3))
    c = list(SimSource(world="room", agent="lidar-1", frames=20, seed=4))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.points, y.points)
        np.testing.assert_array_equal(x.pose, y.pose)
    assert not np.array_equal(a[-1].points, c[-1].points)


def test_without_noise_the_pose_guess_is_the_truth() -> None:
    source = SimSource(
        world="office", agent="depth-1", frames=30, noise=0.0, range_noise=0.0, start="world"
    )
    for obs in source:
        np.testing.assert_allclose(obs.pose, obs.truth, atol=1e-9)
    assert len(source.ground_truth) == 30 and source.stats.delivered == 30


def test_agents_start_at_their_own_origin() -> None:
    first = next(iter(SimSource(world="office", agent="lidar-1", frames=1, noise=0.0)))
    np.testing.assert_allclose(first.odometry, np.eye(4), atol=1e-12)
    assert np.linalg.norm(first.truth[:2, 3]) > 1.0  # the truth is in the site frame


def test_drift_makes_dead_reckoning_wander() -> None:
    def final_error(drift: float) -> float:
        source = SimSource(
            world="room", agent="lidar-1", frames=150, noise=0.0, drift=drift, start="world"
        )
        obs = list(source)[-1]
        return float(np.linalg.norm(obs.pose[:3, 3] - obs.truth[:3, 3]))

    assert final_error(0.0) < 1e-9
    assert final_error(0.05) > 0.2


def test_cctv_reports_landmarks_at_their_true_place() -> None:
    source = SimSource(world="office", agent="cctv-1", frames=1)
    obs = next(iter(source))
    assert len(obs.objects) >= 2
    centres = {m.marker_id: np.asarray(m.centre) for m in source.world.markers}
    for found in obs.objects:
        site = obs.pose @ found.pose
        distance = np.linalg.norm(centres[found.object_id] - obs.pose[:3, 3])
        # small far markers: pose error mostly along the view, a few percent of the distance
        assert np.linalg.norm(site[:3, 3] - centres[found.object_id]) < 0.04 * distance
    assert (obs.class_ids >= 0).any()


def test_a_fixed_cameras_later_frames_are_what_a_fresh_cast_renders() -> None:
    """A fixed camera casts its static scene once; its later frames must be those of a fresh cast
    (same pose, same noise draws)."""
    source = SimSource(world="office", agent="cctv-1", frames=2, seed=4)
    second = list(source)[1]
    rng = np.random.default_rng(4)
    camera = source.adapter.pose  # type: ignore[attr-defined]
    rng.normal(scale=source.range_noise, size=len(source.rig.directions))  # frame 0's noise
    reading = render(source.world, "cctv", source.rig, camera, rng, source.range_noise)
    fresh = source.adapter.observe(reading, pose=None, time=second.time, odometry=None)
    assert np.array_equal(second.points, fresh.points)
    assert np.array_equal(second.colours, fresh.colours)
    assert [o.object_id for o in second.objects] == [o.object_id for o in fresh.objects]


def test_a_depth_agent_with_markers_places_them_by_its_depth() -> None:
    source = SimSource(world="office", agent="depth-1", frames=1, start="world", markers=True)
    obs = next(iter(source))
    assert obs.truth is not None and obs.objects  # the first view holds two tagged pillars
    centres = {m.marker_id: np.asarray(m.centre) for m in source.world.markers}
    for found in obs.objects:
        seen = obs.truth[:3, :3] @ found.position + obs.truth[:3, 3]
        assert found.class_id == 5  # landmark
        assert np.linalg.norm(seen - centres[found.object_id]) < 0.05
    assert not next(iter(SimSource(world="office", agent="depth-1", frames=1))).objects
    with pytest.raises(SourceSpecError, match="markers: expected a depth agent"):
        SimSource(world="office", agent="lidar-1", markers=True)


def test_rendered_depth_agrees_with_ground_truth_geometry() -> None:
    source = SimSource(
        world="room", agent="lidar3d-1", frames=3, range_noise=0.0, noise=0.0, start="world"
    )
    for obs in source:
        pts = obs.points_world()
        assert (np.abs(pts[:, 2]) < 1e-6).sum() > 300  # the floor at z = 0
        assert pts[:, 2].min() > -1e-6
        inside = np.abs(pts[:, :2]).max(axis=1) <= 3.0 + 1e-6
        assert inside.all()


def test_a_depth_frame_comes_back_on_the_planes_it_was_rendered_from() -> None:
    # Render and back-projection agree (intrinsics, principal point, mount): every depth pixel of
    # a camera turned to several yaws, back-projected through the adapter and its pose, lies on
    # one of the scene's planes to a micrometre.
    from plugins.adapter import load_adapter
    from plugins.checks import pose_matrix
    from plugins.sim import make_rig, render
    from plugins.world import Box, World

    world = World(
        "planes", boxes=[Box((3.0, -10, 0), (4.0, 10, 3), 1), Box((-10, -10, 0), (10, -4.0, 3), 1)]
    )
    rig, params = make_rig("depth")
    adapter = load_adapter("depth", **{**params, "mount": rig.mount})
    planes = [(0, 3.0), (1, -4.0), (2, 0.0)]  # axis, offset
    for yaw in (0.0, 0.3, -0.5, -1.2):
        body = pose_matrix(0.2, -1.0, 0.0, yaw)
        frame = render(world, "depth", rig, body @ rig.mount, np.random.default_rng(0), 0.0)
        obs = adapter.observe(frame, pose=body)
        pts = obs.points_world()
        off = np.min(np.abs(np.column_stack([pts[:, a] - c for a, c in planes])), axis=1)
        assert len(pts) > 10000 and off.max() < 1e-6, (yaw, off.max())


def test_several_agents_run_in_real_time() -> None:
    began = time.process_time()  # CPU time: not inflated by other processes on a busy machine
    for name, agent in AGENTS["room"].items():
        for _ in SimSource(
            world="room", agent=name, frames=int(agent.rate)
        ):  # one simulated second each
            pass
    assert time.process_time() - began < 2.0  # one second of four agents within two cores' time


def test_bad_sim_options() -> None:
    with pytest.raises(
        SourceSpecError,
        match=(
            r"agent: expected one of \['cctv-1', 'depth-1', 'lidar-1', 'lidar3d-1'\] in world "
            r"'room', found 'x'"
        ),
    ):
        SimSource(world="room", agent="x")
    with pytest.raises(SourceSpecError, match="start: expected 'origin' or 'world', found 'moon'"):
        SimSource(start="moon")
    with pytest.raises(SourceSpecError, match="frames: expected a whole number >= 1, found 0"):
        SimSource(frames=0)  # no frames: an empty map written as a success before


def test_a_late_reader_skips_frames_unless_told_to_keep_them() -> None:
    # The shared clock started 1 s ago: at 10 frames/s the first 10 frames are past.
    epoch = time.time() - 1.0
    skipped = list(SimSource(world="room", agent="lidar-1", frames=5, epoch=epoch))
    kept = list(SimSource(world="room", agent="lidar-1", frames=5, epoch=epoch, keep_late=True))
    assert skipped == []
    assert [o.time - epoch for o in kept] == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.4])


def test_robots_paths_keep_their_bodies_clear_of_every_solid() -> None:
    # Sampled along one loop of each moving agent's path in each world: the body (a disc of
    # ROBOT_RADIUS) never overlaps a box or cylinder standing on the floor, walls included.
    failures = []
    for world_name in WORLDS:
        world = get_world(world_name)
        boxes = [b for b in world.boxes if b.lo[2] < 1.0 and b.hi[2] > 0.0]
        lo = np.array([b.lo[:2] for b in boxes])
        hi = np.array([b.hi[:2] for b in boxes])
        cylinders = [c for c in world.cylinders if c.z0 < 1.0 and c.z1 > 0.0]
        centres = np.array([c.centre for c in cylinders]).reshape(-1, 2)
        radii = np.array([c.radius for c in cylinders])
        for name, agent in AGENTS[world_name].items():
            if not agent.waypoints:
                continue
            path = Path(agent.waypoints, agent.speed, agent.turn_rate)
            times = np.arange(0.0, path.period, 0.02)
            xy = np.array([path(t)[:2] for t in times])
            gap = np.maximum(np.maximum(lo[None] - xy[:, None], xy[:, None] - hi[None]), 0.0)
            to_box = np.linalg.norm(gap, axis=2)  # (T, boxes): 0 inside
            to_cyl = np.linalg.norm(xy[:, None] - centres[None], axis=2) - radii[None]
            clear = np.minimum(to_box.min(axis=1), to_cyl.min(axis=1, initial=np.inf))
            worst = int(np.argmin(clear))
            if clear[worst] < ROBOT_RADIUS:
                failures.append(
                    f"{world_name} {name} at t={times[worst]:.2f} s, (x, y) = "
                    f"{xy[worst].round(2).tolist()}: {clear[worst]:.3f} m from a solid"
                )
    assert failures == [], f"bodies of radius {ROBOT_RADIUS} m overlap solids: {failures}"


def test_robots_drive_forwards_on_every_loop_of_their_paths() -> None:
    # Over three loops of each moving agent's path, each step's motion is along the body's
    # heading (a ground robot drives forwards, never sideways): a loop ends with a turn back to
    # the first heading. Without it the second loop drove crabwise, 90 degrees off (lidar-1).
    for world_name in WORLDS:
        for name, agent in AGENTS[world_name].items():
            if not agent.waypoints:
                continue
            path = Path(agent.waypoints, agent.speed, agent.turn_rate)
            times = np.arange(0.0, 3 * path.period, 0.1)
            poses = np.array([path(t) for t in times])
            step = np.diff(poses[:, :2], axis=0)
            moving = np.linalg.norm(step, axis=1) > 1e-6
            yaw = poses[:-1, 2][moving]
            sideways = np.abs(-np.sin(yaw) * step[moving, 0] + np.cos(yaw) * step[moving, 1])
            forwards = np.cos(yaw) * step[moving, 0] + np.sin(yaw) * step[moving, 1]
            # a step straddling a waypoint turns as it drives (the sampling): a few mm sideways
            assert sideways.max() < 0.01, f"{world_name} {name} drives sideways"
            assert forwards.min() > 0.0, f"{world_name} {name} drives backwards"
            later = path(2 * path.period + 1.0)
            assert later[:2] == pytest.approx(path(1.0)[:2])
            assert np.cos(later[2] - path(1.0)[2]) == pytest.approx(1.0)
