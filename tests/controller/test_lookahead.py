"""The onboard look ahead: its belief is the simulator's truth where the lidar is exact, and the
controller runs it on every decision as the in-process shield does."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from qnav.contracts import wire
from qnav.contracts.errors import PolicyFileError
from qnav.contracts.lookahead import collision_shares
from qnav.contracts.motion import move_obstacles
from qnav.controller.decision import Controller, Input, Reason
from qnav.controller.lookahead import Lookahead, LookaheadSettings, futures_of
from qnav.controller.perception import TrackerSettings
from qnav.controller.policy import PolicyRuntime
from qnav.lab.oracle import lookahead_model
from qnav.sim.config import WorldConfig, scenario
from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent
from qnav.sim.geometry import cast_rotating_lidar
from qnav.sim.world import WorldState, observe, reset, step
from qnav.simcar.car import scan_message
from qnav.tracking import world_lookahead

DATA = Path(__file__).parents[1] / "data" / "stack"
OBSTACLES_POLICY = DATA / "obstacles-inertia.onnx"
WALLS_POLICY = DATA / "policy.onnx"


def _car(world_name: str) -> Lookahead:
    world = scenario(world_name)
    return world_lookahead(
        world,
        LookaheadSettings(mode="shield"),
        TrackerSettings(),
    )


@pytest.mark.parametrize("world_name", ["obstacles-increment", "obstacles-inertia"])
def test_with_an_exact_lidar_the_belief_is_the_truth_and_so_are_the_risks(world_name: str) -> None:
    world = scenario(world_name)
    car = _car(world_name)
    state = reset(world, np.array([5]), np.array([3]))
    rng = np.random.default_rng(0)
    period = world.control_period_s
    for frame in range(8):
        scan = observe(world, state).scan_m
        assert scan is not None
        car.observe(frame * period, state.pose[0], frame * period, scan[0])
        if frame >= 3:
            belief = car.belief(state.target_xy[0])
            # Every obstacle the lidar sees is tracked where it is, at its velocity.
            seen = np.linalg.norm(state.obstacle_xy[0] - state.pose[0, :2], axis=1) < 6.0
            for xy, velocity in zip(
                state.obstacle_xy[0][seen], state.obstacle_velocity[0][seen], strict=True
            ):
                nearest = np.argmin(np.linalg.norm(belief.obstacle_xy[0] - xy, axis=1))
                np.testing.assert_allclose(belief.obstacle_xy[0, nearest], xy, atol=1e-6)
                np.testing.assert_allclose(
                    belief.obstacle_velocity[0, nearest], velocity, atol=1e-6
                )
            # Its own velocity: exact under increments (none); under inertia, from poses, close
            # once an action has been held (the estimate lags a change of action).
            if frame % 4 == 3:
                np.testing.assert_allclose(belief.velocity[0], state.velocity[0], atol=0.03)
            if world_name == "obstacles-increment":
                tails = rng.integers(0, 3, size=(1, 40, 7))
                model = lookahead_model(world)
                truth = collision_shares(model, state, tails)
                straight = futures_of([car], belief, 1)
                forecast = collision_shares(car.model, belief, tails, straight)
                np.testing.assert_array_equal(forecast, truth)
        state, _, _ = step(world, state, np.array([frame // 4 % 2]))  # forward, then left


def test_the_shield_refuses_a_policy_file_without_a_motion_model_naming_the_fix() -> None:
    runtime = PolicyRuntime(WALLS_POLICY)
    assert not runtime.contract.motion
    with pytest.raises(PolicyFileError, match="qnav export"):
        Controller(runtime, lookahead=LookaheadSettings(mode="shield"))
    Controller(runtime)  # without the shield the file runs as before


def test_the_controller_takes_the_in_process_shields_actions_over_whole_episodes() -> None:
    # The daemon's decision step, fed the simulator's own messages stamped with its clock, and
    # `qnav eval --lookahead shield` on one stream: the same look ahead, the same actions, step
    # by step.
    from qnav.tracking import LookaheadAgent

    world = scenario("obstacles-inertia")
    assert world.lidar is not None
    settings = LookaheadSettings(mode="shield", room_size_m=world.arena.size_m)
    period, test = world.control_period_s, EvalSettings()
    overruled = 0
    # One controller for all episodes, stamped as the lockstep stack stamps them (episode i at
    # (i + 1) * 1000 s): the gap between two episodes' scans restarts its tracking, as the
    # in-process agent restarts with each episode.
    controller = Controller(
        PolicyRuntime(OBSTACLES_POLICY), lookahead=settings, tracker=TrackerSettings()
    )
    for episode in (0, 1, 2):
        overruled_before = controller.counters.overruled
        agent = LookaheadAgent(
            StreamPolicyAgent(PolicyRuntime(OBSTACLES_POLICY), 1),
            world,
            1,
            tracker=TrackerSettings(),
            lookahead=settings,
        )
        agent.start(np.arange(1), np.array([episode]))
        state = reset(world, np.array([test.seed]), np.array([episode]))
        observation = observe(world, state)
        tx, ty = state.target_xy[0]
        for k in range(60):
            now = (episode + 1) * 1000.0 + k * period
            (x, y, yaw), scan = state.pose[0], observation.scan_m
            assert scan is not None
            target = wire.Pose2D(now, "map", tx, ty)
            controller.receive(Input.TARGET, wire.encode_pose_msg(target), now)
            pose = wire.Pose2D(now, "map", x, y, yaw)
            controller.receive(Input.POSE, wire.encode_pose_msg(pose), now)
            message = scan_message(scan[0], now, "laser", world.lidar.max_range_m)
            controller.receive(Input.SCAN, message, now)
            status = controller.decide(now).status
            expected = agent.act(observation)
            if status.reason != Reason.POLICY:
                break
            assert status.action == int(expected[0]), (episode, k, status.risks)
            assert status.risks is not None and len(status.risks) == 3
            state, observation, transition = step(world, state, expected)
            if transition.terminated[0]:
                break
        assert controller.counters.overruled - overruled_before == agent.overruled
        overruled += agent.overruled
    assert overruled > 0, "the look ahead overruled nothing: these episodes test no shield"


def _shielding_controller(world: WorldConfig) -> Controller:
    """A controller running the obstacles policy with the shield, for `world`'s room."""
    settings = LookaheadSettings(mode="shield", room_size_m=world.arena.size_m)
    return Controller(
        PolicyRuntime(OBSTACLES_POLICY),
        lookahead=settings,
        tracker=TrackerSettings(),
    )


def _at_rest(world_name: str, seconds: float) -> tuple[Controller, WorldState, float]:
    """A shielding controller fed `seconds` of scans and poses, no target, while the car stands
    and the obstacles move; the world as it is at the end, and the time."""
    world = scenario(world_name)
    controller = _shielding_controller(world)
    state = reset(world, np.array([EvalSettings().seed]), np.array([4]))
    period, now = world.control_period_s, 0.0
    for k in range(round(seconds / period)):
        now = k * period
        _send_pose_and_scan(controller, world, state, now)
        assert controller.decide(now).status.reason == Reason.NO_TARGET
        xy, velocity = move_obstacles(
            state.obstacle_xy,
            state.obstacle_velocity,
            world.obstacles.radius_m,
            world.arena.size_m,
            period,
        )
        state = state._replace(obstacle_xy=xy, obstacle_velocity=velocity)
    return controller, state, now + period


def _send_pose_and_scan(
    controller: Controller, world: WorldConfig, state: WorldState, now: float
) -> None:
    assert world.lidar is not None
    x, y, yaw = state.pose[0]
    controller.receive(Input.POSE, wire.encode_pose_msg(wire.Pose2D(now, "map", x, y, yaw)), now)
    scan = observe(world, state).scan_m
    assert scan is not None
    message = scan_message(scan[0], now, "laser", world.lidar.max_range_m)
    controller.receive(Input.SCAN, message, now)


def _seen(state: WorldState, within_m: float = 6.0) -> NDArray[np.bool_]:
    return np.asarray(np.linalg.norm(state.obstacle_xy[0] - state.pose[0, :2], axis=1) < within_m)


def test_a_car_at_rest_keeps_tracking_so_its_first_decision_knows_how_obstacles_move() -> None:
    world = scenario("obstacles-inertia")
    controller, state, now = _at_rest(world.name, 1.0)
    _send_pose_and_scan(controller, world, state, now)
    tx, ty = state.target_xy[0]
    controller.receive(Input.TARGET, wire.encode_pose_msg(wire.Pose2D(now, "map", tx, ty)), now)
    assert controller.decide(now).status.reason == Reason.POLICY
    assert controller.lookahead is not None
    belief = controller.lookahead.belief(state.target_xy[0])
    seen = _seen(state)
    assert np.linalg.norm(state.obstacle_velocity[0][seen], axis=1).min() > 0.1  # all move
    for xy, velocity in zip(
        state.obstacle_xy[0][seen], state.obstacle_velocity[0][seen], strict=True
    ):
        nearest = np.argmin(np.linalg.norm(belief.obstacle_xy[0] - xy, axis=1))
        np.testing.assert_allclose(belief.obstacle_xy[0, nearest], xy, atol=1e-6)
        np.testing.assert_allclose(belief.obstacle_velocity[0, nearest], velocity, atol=1e-6)


@pytest.mark.parametrize("gap", ["a pause longer than the scan timeout", "a stamp gone back"])
def test_tracking_starts_again_when_the_scans_break_off(gap: str) -> None:
    world = scenario("obstacles-inertia")
    controller, state, now = _at_rest(world.name, 1.0)
    assert controller.lookahead is not None
    assert np.abs(controller.lookahead.tracker.tracks().velocity_mps).max() > 0.1
    later = now + controller.scan_timeout_s + 0.01 if gap.startswith("a pause") else now - 5.0
    _send_pose_and_scan(controller, world, state, later)
    tracks = controller.lookahead.tracker.tracks()
    assert len(tracks.xy_m) >= _seen(state).sum()
    np.testing.assert_array_equal(tracks.velocity_mps, 0.0)  # every track seen once


def _rotating_scan(
    world: WorldConfig,
    state: WorldState,
    pose_at: Callable[[float], NDArray[np.float64]],
    first_s: float,
    turn_s: float,
) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """The scan a lidar whose turn takes `turn_s` takes from `first_s` on: beam i from the car's
    pose at its own time (`pose_at(t)`), the obstacles where they are then (`state` at time 0)."""
    assert world.lidar is not None
    beams = world.lidar.num_beams
    times_s: NDArray[np.float64] = first_s + turn_s / beams * np.arange(beams, dtype=np.float64)
    poses = np.array([pose_at(t) for t in times_s])
    places, _ = move_obstacles(
        state.obstacle_xy[0],
        state.obstacle_velocity[0],
        world.obstacles.radius_m,
        world.arena.size_m,
        times_s[:, None, None],
    )
    scan = cast_rotating_lidar(poses, world.lidar, world.arena, places, world.obstacles.radius_m)
    return scan, places[-1]


@pytest.mark.parametrize("time_increment", ["sent", "zero"])
def test_a_rotating_lidars_scan_is_placed_beam_by_beam_from_where_the_turning_car_was(
    time_increment: str,
) -> None:
    """A 10 Hz lidar on a car turning at 1 rad/s and driving at 0.5 m/s: its scan's first and
    last beams leave 0.1 rad and 5 cm of the car's motion apart. Placed beam by beam (LaserScan's
    time_increment), every obstacle is tracked where it is and as it moves, and nothing else;
    placed from one pose (time_increment 0, as before), walls become obstacles and the real ones
    are misplaced."""
    world = scenario("obstacles-inertia")
    assert world.lidar is not None
    controller = _shielding_controller(world)
    state = reset(world, np.array([EvalSettings().seed]), np.array([4]))
    start = np.array([5.0, 5.0, 0.3])

    def pose_at(time_s: float) -> NDArray[np.float64]:
        return start + time_s * np.array([0.5 * np.cos(0.3), 0.5 * np.sin(0.3), 1.0])

    turn_s, period, beams = 0.1, 0.2, world.lidar.num_beams
    for k in range(1, 7):
        now = k * period  # the scan ends now; its first beam left turn_s ago
        scan, places = _rotating_scan(world, state, pose_at, now - turn_s, turn_s)
        x, y, yaw = pose_at(now)
        controller.receive(
            Input.POSE, wire.encode_pose_msg(wire.Pose2D(now, "map", x, y, yaw)), now
        )
        increment_s = turn_s / beams if time_increment == "sent" else 0.0
        message = wire.Scan(
            now - turn_s,
            "laser",
            0.0,
            2 * np.pi / beams,
            0.0,
            world.lidar.max_range_m,
            scan.astype(np.float32),
            increment_s,
        )
        controller.receive(Input.SCAN, wire.encode_scan_msg(message), now)
    assert sum(controller.counters.malformed.values()) == 0
    assert controller.lookahead is not None
    tracks = controller.lookahead.tracker.tracks()
    seen = _seen(state._replace(obstacle_xy=places[None], pose=pose_at(now)[None]))
    assert seen.sum() >= 2
    gaps = np.linalg.norm(tracks.xy_m[:, None] - places[seen][None], axis=2)
    if time_increment == "zero":
        assert len(tracks.xy_m) > seen.sum() or gaps.min(axis=0).max() > 0.02
        return
    assert len(tracks.xy_m) == seen.sum()  # no wall taken for an obstacle
    np.testing.assert_allclose(gaps.min(axis=0), 0.0, atol=0.005)
    _, velocity = move_obstacles(
        state.obstacle_xy,
        state.obstacle_velocity,
        world.obstacles.radius_m,
        world.arena.size_m,
        now,
    )
    nearest = gaps.argmin(axis=0)
    np.testing.assert_allclose(tracks.velocity_mps[nearest], velocity[0][seen], atol=0.02)
