"""A room that is not the simulator's (`sim.room`): its ray caster, its spawn law, its obstacles'
shapes and walks, and the paper's scenarios left as they were."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.sim import rng
from qnav.sim.config import ObstacleConfig, WorldConfig, changed_world, scenario
from qnav.sim.room import (
    BOX,
    CYLINDER,
    LEGS,
    bodies,
    cast_rays,
    clutter_boxes,
    inside_room,
    room_clearance,
    room_walls,
    segment_distance,
    static_segments,
    surfaces_at,
)
from qnav.sim.world import BatchedWorld, observe, reset, step

ROOM = scenario("realistic-room")


def _reference_range(
    origin: NDArray[np.float64],
    angle: float,
    circles: NDArray[np.float64],
    segments: NDArray[np.float64],
) -> float:
    """One ray against every circle and segment, solved one by one (np.linalg.solve)."""
    direction = np.array([math.cos(angle), math.sin(angle)])
    best = math.inf
    for x, y, r in circles:
        offset = np.array([x, y]) - origin
        if offset @ offset <= r * r:
            return 0.0
        along = offset @ direction
        disc = along**2 - (offset @ offset - r * r)
        if disc >= 0 and along - math.sqrt(disc) >= 0:
            best = min(best, along - math.sqrt(disc))
    for x0, y0, x1, y1 in segments:
        matrix = np.array([direction, -np.array([x1 - x0, y1 - y0])]).T
        if abs(np.linalg.det(matrix)) < 1e-12:
            continue
        t, s = np.linalg.solve(matrix, np.array([x0, y0]) - origin)
        if t >= 0 and 0 <= s <= 1:
            best = min(best, t)
    return best


def test_the_room_caster_reads_what_a_ray_by_ray_reference_reads() -> None:
    random = np.random.default_rng(3)
    circles = np.concatenate([random.uniform(0, 6, (7, 2)), random.uniform(0.05, 0.5, (7, 1))], 1)
    segments = random.uniform(0, 6, (9, 4))
    origin = np.array([3.0, 3.1])
    angles = np.linspace(0, 2 * math.pi, 240, endpoint=False)
    direction = np.stack([np.cos(angles), np.sin(angles)], -1)[None]
    cast = cast_rays(
        np.broadcast_to(origin, (1, 240, 2)),
        direction,
        circles[None, None],
        [segments[None, None]],
        max_range_m=20.0,
    )[0]
    reference = np.array([_reference_range(origin, a, circles, segments) for a in angles])
    assert np.isfinite(reference).sum() > 100  # the rays meet things
    np.testing.assert_allclose(cast, reference, atol=1e-4)


def test_a_ray_from_inside_a_circle_reads_zero_and_nothing_in_range_reads_inf() -> None:
    origin = np.zeros((1, 2, 2))
    direction = np.array([[[1.0, 0.0], [-1.0, 0.0]]])
    inside = cast_rays(origin, direction, np.array([[[[0.1, 0.0, 0.5]]]]), [], 20.0)
    far = cast_rays(origin, direction, np.array([[[[30.0, 0.0, 1.0]]]]), [], 20.0)
    assert inside.tolist() == [[0.0, 0.0]]
    assert np.isinf(far).all()


def test_the_room_spawns_inside_its_walls_clear_of_clutter_and_obstacles() -> None:
    n = 400
    state = reset(ROOM, np.full(n, 5), np.arange(n))
    keys = rng.episode_keys(state.seed, state.episode)
    statics = static_segments(ROOM, clutter_boxes(ROOM, keys))
    margin = ROOM.spawn.wall_margin_m
    for xy in (state.pose[:, :2], state.target_xy):
        assert inside_room(ROOM, xy).all()
        assert segment_distance(xy[:, None], statics[:, None]).min() >= margin - 1e-9
    distance = np.linalg.norm(state.target_xy - state.pose[:, :2], axis=1)
    assert distance.min() >= 0.5 and distance.max() <= 3.0
    static, moving = room_clearance(ROOM, state)
    assert static.min() >= margin - 1e-9
    assert moving.min() >= ROOM.spawn.obstacle_clearance_m - 1e-9
    assert inside_room(ROOM, state.obstacle_xy).all()


def test_the_room_runs_the_same_alone_as_inside_a_batch() -> None:
    batch = BatchedWorld(ROOM, 6, seed=20)
    alone = BatchedWorld(ROOM, 1, seed=23)
    actions = np.random.default_rng(0).integers(0, 3, (25, 6))
    for action in actions:
        together = batch.step(action).observation
        single = alone.step(action[3:4]).observation
        assert together.scan_m is not None and single.scan_m is not None
        np.testing.assert_array_equal(together.scan_m[3], single.scan_m[0])
        np.testing.assert_array_equal(together.pose[3], single.pose[0])


def test_obstacles_are_cylinders_boxes_and_legs_in_their_shares_with_radii_in_range() -> None:
    keys = rng.episode_keys(np.full(2000, 1), np.arange(2000))
    shapes = bodies(ROOM, keys)
    shares = [float(np.mean(shapes.kind == kind)) for kind in (CYLINDER, BOX, LEGS)]
    assert shares == pytest.approx([1 / 3] * 3, abs=0.03)
    sized = shapes.half[shapes.kind != LEGS]
    assert sized.min() >= 0.15 and sized.max() <= 0.3
    assert sized.std() > 0.03  # drawn, not one size


def test_a_box_obstacle_collides_at_its_side_not_at_a_circle_round_it() -> None:
    world = changed_world(
        scenario("obstacles-inertia"),
        None,
        ["obstacles.count=1", "obstacles.box_share=1", "obstacles.radius_max_m=0.3"],
    )
    state = reset(world, np.array([2]), np.array([0]))
    shapes = bodies(world, rng.episode_keys(state.seed, state.episode))
    half_length = shapes.half[0, 0, 0]
    # The robot just off the box's front face, on its axis (the box faces its velocity).
    heading = np.arctan2(state.obstacle_velocity[0, 0, 1], state.obstacle_velocity[0, 0, 0])
    ahead = np.array([np.cos(heading), np.sin(heading)])
    robot = state.obstacle_xy[0, 0] + (half_length + 0.7) * ahead
    placed = state._replace(pose=np.array([[*robot, heading + math.pi]]))
    _, moving = room_clearance(world, placed)
    assert moving[0] == pytest.approx(0.7, abs=1e-9)


def test_a_heading_walk_turns_each_obstacle_by_its_spread_every_period() -> None:
    world = changed_world(scenario("obstacles-inertia"), None, ["obstacles.heading_walk_rad=0.3"])
    state = reset(world, np.full(200, 4), np.arange(200))
    assert state.obstacle_motion is not None
    turns = []
    for _ in range(3):
        before = state.obstacle_motion
        assert before is not None
        state, _, _ = step(world, state, np.zeros(200, dtype=np.int64))
        assert state.obstacle_motion is not None
        turn = np.angle(np.exp(1j * (state.obstacle_motion[..., 0] - before[..., 0])))
        speed = np.linalg.norm(state.obstacle_velocity, axis=-1)
        assert speed.min() >= 0.5  # nothing stops without stop_probability
        turns.append(turn[np.abs(turn) < 1.2])  # a bounce off a wall turns by more
    spread = np.concatenate(turns).std()
    assert spread == pytest.approx(0.3, abs=0.03)


def test_stopping_obstacles_stand_still_and_walk_on_later() -> None:
    world = changed_world(
        scenario("obstacles-inertia"),
        None,
        ["obstacles.stop_probability=0.2", "obstacles.start_probability=0.5"],
    )
    state = reset(world, np.full(50, 4), np.arange(50))
    standing = []
    for _ in range(20):
        before = state.obstacle_xy
        state, _, _ = step(world, state, np.zeros(50, dtype=np.int64))
        still = np.linalg.norm(state.obstacle_xy - before, axis=-1) == 0
        standing.append(still)
    shares = np.mean(standing[5:], axis=(1, 2))
    # Walking -> standing at 0.2, standing -> walking at 0.5: 2/7 of them stand in the long run.
    assert shares.mean() == pytest.approx(2 / 7, abs=0.05)
    walked_on = np.stack(standing)[:-1] & ~np.stack(standing)[1:]
    assert walked_on.sum() > 100


def test_walking_obstacles_stay_inside_the_polygon_room_and_off_the_clutter() -> None:
    world = replace(ROOM, lidar_turn_s=0.0, sensor=replace(ROOM.sensor, lidar_readings=0))
    state = reset(world, np.full(32, 8), np.arange(32))
    keys = rng.episode_keys(state.seed, state.episode)
    statics = static_segments(world, clutter_boxes(world, keys))
    reach = bodies(world, keys).bounding_m()
    for _ in range(150):
        state, _, _ = step(world, state, np.full(32, 1, dtype=np.int64))
        assert inside_room(world, state.obstacle_xy).all()
        gaps = segment_distance(state.obstacle_xy, statics[:, None]).min(-1)
        assert (gaps >= reach - 1e-9).all()


def test_the_room_walls_are_the_polygons_sides() -> None:
    walls = room_walls(ROOM)
    assert walls.shape == (6, 4)
    assert walls[-1].tolist() == [0.0, 8.0, 0.0, 0.0]


def test_the_lidar_sees_the_clutter_and_a_collision_with_it_ends_the_episode() -> None:
    world = replace(ROOM, obstacles=ObstacleConfig(count=0))
    state = reset(world, np.array([11]), np.array([0]))
    keys = rng.episode_keys(state.seed, state.episode)
    box = clutter_boxes(world, keys)[0, 0]
    # The robot 0.3 m from the box's centre: inside the robot's radius of its sides.
    placed = state._replace(pose=np.array([[box[0] + 0.3, box[1], 0.0]]))
    observation = observe(world, placed)
    assert observation.clearance_m[0] < world.robot_radius_m
    _, _, transition = step(world, placed, np.array([1]))
    assert transition.outcome[0] == Outcome.COLLISION
    surfaces = surfaces_at(world, state, np.zeros(1))
    assert surfaces.statics.shape[2] == 6 + 4 * 4  # the walls and the clutter's sides


@pytest.mark.parametrize("name", ["obstacles-inertia", "walls-increment", "obstacles-increment"])
def test_the_papers_scenarios_have_no_realistic_setting_on(name: str) -> None:
    world: WorldConfig = scenario(name)
    assert not world.realistic and not world.obstacles.walks
    assert not world.sensor.scan_effects and not world.sensor.pose_effects
    assert reset(world, np.array([1]), np.array([0])).obstacle_motion is None
