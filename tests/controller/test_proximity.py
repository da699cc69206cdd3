"""The proximity stop (controller.proximity): its field is what the car sweeps, and no policy or
look ahead drives into it; real controllers on the committed obstacles policy, real scans."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from qnav.contracts import wire
from qnav.contracts.actions import Action
from qnav.contracts.errors import ConfigError
from qnav.contracts.wire import STOP, Twist2D
from qnav.controller.decision import Controller, Input, Output, Reason
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.policy import PolicyRuntime
from qnav.controller.proximity import (
    Blocked,
    ProximitySettings,
    allowed_actions,
    blocked_parts,
    field_ranges,
    footprint_mismatch,
    guarded_action,
)

OBSTACLES_POLICY = Path(__file__).parents[1] / "data" / "stack" / "obstacles-inertia.onnx"
BARN_POLICY = Path(__file__).parents[2] / "results" / "barn" / "barn-recurrent.onnx"
BEAMS = 720
ROOM_M = 10.0
FOOTPRINT_M, TRAVEL_M = ProximitySettings().footprint_m, ProximitySettings().travel_m
ANGLES = 2 * math.pi / BEAMS * np.arange(BEAMS) - math.pi  # a scan over [-pi, pi)
FORWARD_TURN_TURN = np.array([0.5, 0.0, 0.0])  # the forward speed of each action


def swept_by_the_car(x: float, y: float, footprint_m: float, travel_m: float) -> bool:
    """Brute force: the car's disc, moved straight ahead in 1 mm steps up to `travel_m`, covers
    the point, which lies ahead of the centre."""
    centres = np.linspace(0.0, travel_m, max(2, round(travel_m * 1000) + 1))
    return x > 0 and bool((np.hypot(x - centres, y) < footprint_m).any())


def room_ranges(x: float, y: float, yaw: float) -> NDArray[np.float32]:
    """Each reading of a scan over [-pi, pi) from (x, y, yaw) in the empty square room."""
    heading = yaw + ANGLES
    cos, sin = np.cos(heading), np.sin(heading)
    with np.errstate(divide="ignore"):
        to_x = np.where(cos > 0, (ROOM_M - x) / cos, np.where(cos < 0, -x / cos, np.inf))
        to_y = np.where(sin > 0, (ROOM_M - y) / sin, np.where(sin < 0, -y / sin, np.inf))
    return np.minimum(to_x, to_y).astype(np.float32)


def scan_payload(ranges: NDArray[np.float32], stamp: float, range_min: float = 0.05) -> bytes:
    return wire.encode_scan_msg(
        wire.Scan(stamp, "laser", -math.pi, 2 * math.pi / BEAMS, range_min, 30.0, ranges)
    )


def a_person_ahead(ranges: NDArray[np.float32], distance_m: float) -> NDArray[np.float32]:
    """The readings of a person 0.3 m wide standing `distance_m` straight ahead."""
    person = ranges.copy()
    person[np.abs(ANGLES) < math.atan2(0.15, distance_m)] = distance_m
    return person


def controller(lookahead: LookaheadSettings | None = None) -> Controller:
    return Controller(
        PolicyRuntime(OBSTACLES_POLICY), lookahead=lookahead, proximity=ProximitySettings()
    )


def decide_on(
    c: Controller, ranges: NDArray[np.float32], now: float, pose: tuple[float, float, float]
) -> Output:
    """Give the controller the target (8, 5), the pose and the scan at `now`, and decide."""
    c.receive(Input.TARGET, wire.encode_pose_msg(wire.Pose2D(now, "map", 8.0, 5.0)), now)
    c.receive(Input.POSE, wire.encode_pose_msg(wire.Pose2D(now, "map", *pose)), now)
    assert c.receive(Input.SCAN, scan_payload(ranges, now), now) is None
    return c.decide(now)


def assert_proximity_stop(output: Output) -> None:
    assert output.status.reason is Reason.PROXIMITY
    assert output.command == STOP and output.status.action is None


def test_the_travel_field_is_what_the_cars_disc_sweeps_driving_straight_on() -> None:
    points = np.random.default_rng(0).uniform(-1.2, 1.2, size=(3000, 2))
    for x, y in points:
        angle, distance = np.array([math.atan2(y, x)]), np.array([math.hypot(x, y)])
        blocked = blocked_parts(angle, distance, FOOTPRINT_M, TRAVEL_M)
        assert blocked.ahead == swept_by_the_car(x, y, FOOTPRINT_M, TRAVEL_M), (x, y)
        assert blocked.behind == swept_by_the_car(-x, y, FOOTPRINT_M, TRAVEL_M), (x, y)
        assert blocked.footprint == (math.hypot(x, y) < FOOTPRINT_M), (x, y)


def test_a_turn_in_place_is_forbidden_only_by_something_inside_the_footprint() -> None:
    forward, left, right = 0, 1, 2
    for blocked, allowed in [
        (Blocked(footprint=False, ahead=True, behind=False), [False, True, True]),
        (Blocked(footprint=False, ahead=False, behind=True), [True, True, True]),
        (Blocked(footprint=True, ahead=True, behind=True), [False, False, False]),
    ]:
        assert allowed_actions(FORWARD_TURN_TURN, blocked).tolist() == allowed
    reverse = np.array([-0.5, 0.0, 0.0])  # a backward action has the mirrored field
    assert not allowed_actions(reverse, Blocked(False, False, True))[forward]
    assert allowed_actions(reverse, Blocked(False, True, False))[[forward, left, right]].all()


def test_neg_inf_and_readings_below_range_min_are_at_the_lidar_unless_they_mean_no_echo() -> None:
    readings = np.array([-np.inf, 0.0, 0.05, 0.3, np.nan, np.inf, 40.0], dtype=np.float32)
    np.testing.assert_array_equal(
        field_ranges(readings, 0.1, 30.0, below_min_is_no_return=False),
        [0.0, 0.0, 0.0, np.float32(0.3), np.nan, np.nan, np.nan],
    )
    np.testing.assert_array_equal(
        field_ranges(readings, 0.1, 30.0, below_min_is_no_return=True),
        [0.0, np.nan, np.nan, np.float32(0.3), np.nan, np.nan, np.nan],
    )


def test_a_forbidden_action_gives_way_to_the_best_allowed_one_and_none_allowed_is_a_stop() -> None:
    q = np.array([3.0, 2.0, 1.0])
    allowed = np.array([False, True, True])
    assert guarded_action(1, allowed, q) == 1  # allowed: kept, whatever its value
    assert guarded_action(0, allowed, q) == 1  # the best-valued allowed action
    # With the shield's risks, the shield's rule among the allowed actions: the best-valued
    # one is too risky (0.5 >= 0.3), so the best-valued among the least risky.
    assert guarded_action(0, allowed, q, np.array([0.0, 0.5, 0.2]), 0.3) == 2
    assert guarded_action(0, allowed, q, np.array([0.0, 0.1, 0.2]), 0.3) == 1
    assert guarded_action(2, np.zeros(3, dtype=bool), q) is None


@pytest.mark.parametrize("mode", ["off", "shield"])
def test_an_all_neg_inf_scan_stops_the_car_whatever_the_policy_and_look_ahead_chose(
    mode: str,
) -> None:
    c = controller(LookaheadSettings(mode=mode, room_size_m=ROOM_M))  # type: ignore[arg-type]
    output = decide_on(c, np.full(BEAMS, -np.inf, np.float32), 0.0, (2.0, 5.0, 0.0))
    assert_proximity_stop(output)
    assert output.status.q_values is not None  # the policy did decide
    counters = output.status.to_dict()["counters"]
    assert counters["proximity"] == 1 and counters["stops"] == 1


@pytest.mark.parametrize("mode", ["off", "shield"])
def test_a_wall_a_tenth_of_a_metre_ahead_stops_the_car(mode: str) -> None:
    c = controller(LookaheadSettings(mode=mode, room_size_m=ROOM_M))  # type: ignore[arg-type]
    pose = (ROOM_M - 0.1, 5.0, 0.0)  # facing the east wall, 0.1 m from it
    for step in range(3):
        assert_proximity_stop(decide_on(c, room_ranges(*pose), 0.2 * step, pose))
    assert c.counters.proximity == 3


def test_a_person_stepping_in_front_while_the_policy_says_forward_turns_or_stops_the_car() -> None:
    c = controller()
    pose = (2.0, 5.0, 0.0)  # facing the target (8, 5) across the empty room
    clear = room_ranges(*pose)
    driving = decide_on(c, clear, 0.0, pose)
    assert driving.status.reason is Reason.POLICY and driving.status.action is Action.FORWARD
    stepped_in = decide_on(c, a_person_ahead(clear, 0.7), 0.2, pose)
    assert stepped_in.status.reason is Reason.PROXIMITY
    q = stepped_in.status.q_values
    assert q is not None and int(np.argmax(q)) == Action.FORWARD  # the policy still says forward
    turns = {Twist2D(a.linear_mps, a.angular_radps) for a in c.runtime.contract.actions[1:]}
    assert stepped_in.command in turns  # turning away is safe: the footprint is clear
    assert stepped_in.status.action is Action(1 + int(np.argmax(q[1:])))  # the better turn
    assert c.counters.proximity == 1
    gone = decide_on(c, clear, 0.4, pose)
    assert gone.status.reason is Reason.POLICY and c.counters.proximity == 1


def test_the_proximity_stop_keeps_the_policys_window_going() -> None:
    # The policy decided on the frame: the stop changes the command, not the policy's episode.
    stopped, plain = controller(), controller()
    plain.proximity = ProximitySettings(enabled=False)
    pose = (2.0, 5.0, 0.0)
    clear = room_ranges(*pose)
    frames = [clear, np.full(BEAMS, -np.inf, np.float32), clear, clear]
    for step, ranges in enumerate(frames):
        a, b = (
            decide_on(stopped, ranges, 0.2 * step, pose),
            decide_on(plain, ranges, 0.2 * step, pose),
        )
        assert a.status.q_values == b.status.q_values
    assert stopped.counters.proximity == 1 and plain.counters.proximity == 0


def test_proximity_settings_out_of_range_name_the_setting() -> None:
    with pytest.raises(ConfigError, match=r"proximity\.footprint_m"):
        ProximitySettings(footprint_m=-0.1)
    with pytest.raises(ConfigError, match=r"proximity\.travel_m"):
        ProximitySettings(travel_m=math.nan)


def test_a_safety_field_that_does_not_fit_the_policys_robot_is_named_either_way() -> None:
    assert footprint_mismatch(0.5, 0.5) is None and footprint_mismatch(0.33, 0.3) is None
    larger = footprint_mismatch(0.5, 0.3)
    assert larger is not None and "proximity.footprint_m = 0.5 m" in larger
    assert "radius 0.3 m" in larger and "hold the car in gaps" in larger
    smaller = footprint_mismatch(0.2, 0.5)
    assert smaller is not None and "larger robot than the field protects" in smaller


def test_the_daemon_warns_when_the_shipped_field_does_not_fit_the_policys_robot(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The BARN policy (a 0.3 m robot) under the shipped 0.5 m field: logged at start, naming
    the setting; with the field set to its radius, nothing."""
    from qnav.controller.config import ControllerSettings, DaemonConfig
    from qnav.controller.daemon import build

    for footprint_m, warned in ((0.5, True), (0.3, False)):
        caplog.clear()
        config = DaemonConfig(
            controller=ControllerSettings(policy=str(BARN_POLICY)),
            proximity=ProximitySettings(footprint_m=footprint_m),
            lookahead=LookaheadSettings(room_size_m=10.0),
        )
        build(config)
        warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        assert any("proximity.footprint_m" in w for w in warnings) is warned, warnings
