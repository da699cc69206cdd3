"""The decision step without I/O (controller.decision): each safety rule, and the policy's path."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from qnav.contracts import cdr, delivery, wire
from qnav.contracts.errors import PolicyFileError
from qnav.contracts.wire import STOP, Pose2D, Scan, Twist2D
from qnav.controller.config import LidarSettings, SafetySettings
from qnav.controller.decision import Controller, Input, Output, Reason
from qnav.controller.policy import PolicyRuntime
from tests.conftest import PolicyFactory
from tests.contracts.malformed import CANONICAL_TRUE

PERIOD = 0.2  # the scenarios' control period


def scan_payload(stamp: float = 0.0, frame: str = "laser", count: int = 1080) -> bytes:
    ranges = np.random.default_rng(0).uniform(0.5, 8.0, count).astype(np.float32)
    return wire.encode_scan_msg(Scan(stamp, frame, -math.pi, 2 * math.pi / count, 0.1, 30, ranges))


def pose_payload(x: float = 1.0, y: float = 1.0, yaw: float = 0.3, frame: str = "map") -> bytes:
    return wire.encode_pose_msg(Pose2D(0.0, frame, x, y, yaw))


def target_payload(x: float = 8.0, y: float = 8.0, frame: str = "map") -> bytes:
    return wire.encode_pose_msg(Pose2D(0.0, frame, x, y))


def odd_scan_payload(range_min: float, range_max: float, count: int = 1080) -> bytes:
    ranges = np.full(count, 3.0, dtype=np.float32)
    return wire.encode_scan_msg(
        Scan(0.0, "laser", -math.pi, 2 * math.pi / count, range_min, range_max, ranges)
    )


def pose_with_quaternion(qx: float, qy: float, qz: float, qw: float) -> bytes:
    writer = cdr.Writer()
    writer.pack(cdr.TIME, 4, 0, 0)
    writer.string("map")
    writer.pack(cdr.Layout("7d"), 8, 1.0, 1.0, 0.0, qx, qy, qz, qw)
    return writer.payload()


def quaternion_payload(w: float) -> bytes:
    """A PoseStamped whose orientation is (0, 0, 0, w)."""
    return pose_with_quaternion(0.0, 0.0, 0.0, w)


@pytest.fixture
def policy(make_policy: PolicyFactory) -> Path:
    return make_policy("walls-inertia")


def controller(policy: Path, **safety: object) -> Controller:
    return Controller(PolicyRuntime(policy), SafetySettings(**safety))  # type: ignore[arg-type]


def feed(c: Controller, now: float, scan: bool = True, pose: bool = True) -> None:
    if scan:
        assert c.receive(Input.SCAN, scan_payload(now), now) is None
    if pose:
        assert c.receive(Input.POSE, pose_payload(), now) is None


def ready(policy: Path, **safety: object) -> Controller:
    c = controller(policy, **safety)
    assert c.receive(Input.TARGET, target_payload(), 0.0) is None
    feed(c, 0.0)
    return c


def assert_stop(output: Output, reason: Reason) -> None:
    assert output.status.reason is reason
    assert output.command == STOP
    assert output.status.action is None and output.status.q_values is None


def test_fresh_inputs_let_the_policy_command_its_actions_velocity(policy: Path) -> None:
    c = ready(policy)
    output = c.decide(0.05)
    assert output.status.reason is Reason.POLICY
    assert output.status.action is not None and output.status.q_values is not None
    velocity = c.runtime.contract.actions[output.status.action]
    assert output.command == Twist2D(velocity.linear_mps, velocity.angular_radps)
    assert int(np.argmax(output.status.q_values)) == output.status.action


def test_the_policy_sees_what_a_runtime_fed_the_same_observation_sees(policy: Path) -> None:
    from qnav.contracts.observation import target_features
    from qnav.controller.scan import ScanRules, resample_scan

    c = ready(policy)
    q = c.decide(0.05).status.q_values
    runtime = PolicyRuntime(policy)
    scan = resample_scan(wire.decode_scan_msg(scan_payload()), ScanRules(720)).ranges_m
    expected = runtime.step(scan, target_features(np.array([1.0, 1.0, 0.3]), np.array([8, 8])))
    assert q is not None
    np.testing.assert_allclose(np.array(q), expected.q_values, rtol=1e-6)


def test_nothing_moves_the_car_before_every_input_has_arrived(policy: Path) -> None:
    c = controller(policy)
    assert_stop(c.decide(0.0), Reason.NO_SCAN)
    c.receive(Input.SCAN, scan_payload(), 0.0)
    assert_stop(c.decide(0.01), Reason.NO_POSE)
    c.receive(Input.POSE, pose_payload(), 0.01)
    assert_stop(c.decide(0.02), Reason.NO_TARGET)
    c.receive(Input.TARGET, target_payload(), 0.02)
    assert c.decide(0.03).status.reason is Reason.POLICY


def test_a_scan_older_than_two_control_periods_stops_the_car(policy: Path) -> None:
    c = ready(policy)
    assert c.decide(2 * PERIOD - 1e-6).status.reason is Reason.POLICY
    c.receive(Input.POSE, pose_payload(), 2 * PERIOD)
    output = c.decide(2 * PERIOD + 1e-3)
    assert_stop(output, Reason.SCAN_STALE)
    assert output.status.ages_s["scan"] == pytest.approx(2 * PERIOD + 1e-3)


def test_a_pose_older_than_two_control_periods_stops_the_car(policy: Path) -> None:
    c = ready(policy)
    c.receive(Input.SCAN, scan_payload(), 2 * PERIOD)
    assert_stop(c.decide(2 * PERIOD + 1e-3), Reason.POSE_STALE)


def test_configured_timeouts_replace_two_control_periods(policy: Path) -> None:
    c = ready(policy, scan_timeout_s=1.0, pose_timeout_s=0.1)
    assert_stop(c.decide(0.11), Reason.POSE_STALE)
    c.receive(Input.POSE, pose_payload(), 0.9)
    assert c.decide(0.95).status.reason is Reason.POLICY
    c.receive(Input.POSE, pose_payload(), 1.0)
    assert_stop(c.decide(1.01), Reason.SCAN_STALE)


def test_the_car_stops_at_the_target_until_a_different_target_arrives(policy: Path) -> None:
    c = ready(policy, target_tolerance_m=0.3)
    c.receive(Input.TARGET, target_payload(1.2, 1.1), 0.0)
    output = c.decide(0.01)
    assert_stop(output, Reason.TARGET_REACHED)
    assert output.status.target_distance_m == pytest.approx(math.hypot(0.2, 0.1))
    c.receive(Input.POSE, pose_payload(x=3.0), 0.02)  # pushed away: still done
    c.receive(Input.TARGET, target_payload(1.2, 1.1), 0.02)  # the same target again
    assert_stop(c.decide(0.03), Reason.TARGET_REACHED)
    c.receive(Input.TARGET, target_payload(5.0, 5.0), 0.04)
    assert c.decide(0.05).status.reason is Reason.POLICY


@pytest.mark.parametrize(
    ("source", "payload"),
    [
        pytest.param(Input.SCAN, b"", id="scan-empty"),
        pytest.param(Input.SCAN, b"\x00\x01\x00\x00" + b"\x07" * 40, id="scan-garbage"),
        pytest.param(Input.SCAN, scan_payload()[:-9], id="scan-truncated"),
        pytest.param(Input.SCAN, pose_payload(), id="scan-another-type"),
        pytest.param(
            Input.POSE, wire.encode_pose_msg(Pose2D(0.0, "map", math.nan, 1.0)), id="pose-nan"
        ),
        pytest.param(
            Input.POSE, wire.encode_pose_msg(Pose2D(0.0, "map", 1.0, math.inf)), id="pose-inf"
        ),
        pytest.param(Input.POSE, b"\x00\x01", id="pose-truncated"),
        pytest.param(Input.POSE, pose_payload(x=1e308), id="pose-absurd"),
        pytest.param(Input.POSE, pose_payload(y=-1001.0), id="pose-beyond-max-position"),
        pytest.param(Input.POSE, quaternion_payload(2.0), id="pose-quaternion-norm-2"),
        pytest.param(Input.POSE, quaternion_payload(0.0), id="pose-zero-quaternion"),
        pytest.param(Input.TARGET, target_payload(x=-1e308), id="target-absurd"),
        pytest.param(Input.SCAN, odd_scan_payload(math.nan, 30.0), id="scan-range-min-nan"),
        pytest.param(Input.SCAN, odd_scan_payload(0.1, math.nan), id="scan-range-max-nan"),
        pytest.param(Input.SCAN, odd_scan_payload(5.0, 1.0), id="scan-range-min-above-max"),
        pytest.param(Input.SCAN, odd_scan_payload(0.1, 30.0, count=1), id="scan-one-reading"),
        pytest.param(Input.SCAN, odd_scan_payload(0.1, 30.0, count=49), id="scan-49-readings"),
        pytest.param(
            Input.TARGET, wire.encode_pose_msg(Pose2D(0.0, "map", math.nan, 1.0)), id="target-nan"
        ),
        pytest.param(Input.TARGET, scan_payload()[:30], id="target-garbage"),
        pytest.param(Input.ESTOP_RELEASE, b"", id="release-empty"),
        pytest.param(Input.ESTOP_RELEASE, bytes.fromhex("0001000002"), id="release-bool-2"),
        pytest.param(
            Input.TARGET, wire.encode_pose_msg(Pose2D(0.0, "map", 1.0, -1001.0)), id="target-far"
        ),
    ],
)
def test_a_malformed_payload_is_counted_and_keeps_the_last_good_input(
    policy: Path, source: Input, payload: bytes
) -> None:
    c = ready(policy)
    reference = ready(policy)
    received = c.counters.received[source.value]
    assert c.receive(source, payload, 0.1)
    status = c.decide(0.1).status
    assert status.counters["received"][source.value] == received + 1
    assert status.counters["malformed"][source.value] == 1
    assert status.q_values == reference.decide(0.1).status.q_values
    # The age is still that of the last good input (arrived at 0.0; the release never).
    good_age = None if source is Input.ESTOP_RELEASE else 0.1
    assert status.ages_s[source.value] == good_age


@pytest.mark.parametrize(
    "quaternion", [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 2.0), (0.0, 0.0, 0.5, 0.5)]
)
def test_a_pose_whose_quaternion_is_not_a_unit_one_is_malformed(
    policy: Path, quaternion: tuple[float, float, float, float]
) -> None:
    c = ready(policy)
    assert "quaternion" in (c.receive(Input.POSE, pose_with_quaternion(*quaternion), 0.1) or "")
    assert c.counters.malformed["pose"] == 1
    assert c.receive(Input.POSE, pose_with_quaternion(0.0, 0.0, 0.0, 1.0), 0.1) is None


def test_a_position_beyond_safety_max_position_m_is_malformed(policy: Path) -> None:
    c = ready(policy, max_position_m=50.0)
    assert c.receive(Input.POSE, pose_payload(x=30.0, y=-40.0), 0.1) is None
    error = c.receive(Input.POSE, pose_payload(x=50.5), 0.15)
    assert error is not None and "safety.max_position_m = 50.0" in error
    assert "safety.max_position_m" in (c.receive(Input.TARGET, target_payload(y=-51.0), 0.15) or "")
    assert c.counters.malformed["pose"] == 1 and c.counters.malformed["target"] == 1
    assert c.decide(0.15).status.target_distance_m == pytest.approx(math.hypot(8 - 30, 8 + 40))


def test_a_malformed_message_on_the_estop_topic_presses_the_stop(policy: Path) -> None:
    for index, payload in enumerate(
        [b"\xff", b"", bytes.fromhex("0001000002"), bytes.fromhex("0001ffff00"), scan_payload()]
    ):
        c = ready(policy)
        assert c.decide(0.05).status.reason is Reason.POLICY
        error = c.receive(Input.ESTOP, payload, 0.06)
        assert error is not None and "taken as a press" in error, index
        output = c.decide(0.07)
        assert_stop(output, Reason.ESTOP_LATCHED)
        assert (output.status.estop_latched, output.status.estop_pressed) == (True, True)
        counters = output.status.counters
        assert counters["malformed"]["estop"] == 1 and counters["estop_presses"] == 1
        assert output.status.ages_s["estop"] is None  # no well-formed estop message yet
        # Pressed: a release is refused until a well-formed false says the button is out.
        assert c.receive(Input.ESTOP_RELEASE, wire.encode_bool_msg(True), 0.08)
        assert c.counters.releases_refused == 1
        assert c.receive(Input.ESTOP, wire.encode_bool_msg(False), 0.09) is None
        assert_stop(c.decide(0.09), Reason.ESTOP_LATCHED)
        assert c.receive(Input.ESTOP_RELEASE, wire.encode_bool_msg(True), 0.1) is None
        feed(c, 0.1)
        assert c.decide(0.11).status.reason is Reason.POLICY


RELEASE_LOOKALIKES = [
    "0001000002",  # value byte 2
    "00010000ff",
    "0001000080000000",
    "0001000001deadbe",  # garbage after the value
    "0001ffff01",  # non-zero options
    "0000000002",  # big-endian, value byte 2
    "000100000100000000",  # more than alignment padding
    "00010000",  # no value
    "000100000101",  # a second byte
    "0001000201000000",  # options announce 2 padding bytes, 3 follow
]


@pytest.mark.parametrize("payload", RELEASE_LOOKALIKES)
def test_a_malformed_release_never_releases(policy: Path, payload: str) -> None:
    """The first five released a latched stop with the button out when issue 18 was filed;
    the rest are lookalikes of a canonical true. The canonical ones still release."""
    c = ready(policy)
    c.receive(Input.ESTOP, wire.encode_bool_msg(True), 0.01)
    c.receive(Input.ESTOP, wire.encode_bool_msg(False), 0.02)
    assert c.receive(Input.ESTOP_RELEASE, bytes.fromhex(payload), 0.03)
    feed(c, 0.03)
    assert_stop(c.decide(0.04), Reason.ESTOP_LATCHED)
    assert c.counters.malformed["estop_release"] == 1
    for canonical in ("0001000001", "0001000301000000"):  # padded as Cyclone DDS writes it
        c = ready(policy, estop_start_latched=True)
        assert c.receive(Input.ESTOP_RELEASE, bytes.fromhex(canonical), 0.03) is None
        assert c.decide(0.04).status.reason is Reason.POLICY


def scan_layout(
    count: int = 720,
    increment: float = 2 * math.pi / 720,
    range_min: float = 0.1,
    range_max: float = 30.0,
    time_increment: float = 0.0,
) -> bytes:
    ranges = np.full(count, 3.0, dtype=np.float32)
    return wire.encode_scan_msg(
        Scan(0.0, "laser", 0.0, increment, range_min, range_max, ranges, time_increment)
    )


@pytest.mark.parametrize(
    ("payload", "why"),
    [
        pytest.param(scan_layout(range_min=math.nan), "range_min", id="range-min-nan"),
        pytest.param(scan_layout(range_max=math.nan), "range_min", id="range-max-nan"),
        pytest.param(scan_layout(range_max=math.inf), "range_min", id="range-max-inf"),
        pytest.param(scan_layout(range_min=5.0, range_max=5.0), "range_min", id="min-equals-max"),
        pytest.param(scan_layout(range_min=-1.0), "range_min", id="range-min-negative"),
        pytest.param(scan_layout(count=1, increment=0.01), "min_readings", id="one-reading"),
        pytest.param(scan_layout(count=49, increment=0.1), "min_readings", id="49-readings"),
        pytest.param(scan_layout(count=300, increment=0.01), "min_field_of_view", id="narrow"),
        # Readings spread over a second: longer than the scan timeout (two 0.2 s periods).
        pytest.param(scan_layout(time_increment=1 / 719), "scan_timeout_s", id="slow-turn"),
    ],
)
def test_a_scan_that_no_planar_lidar_sends_is_malformed(
    policy: Path, payload: bytes, why: str
) -> None:
    c = ready(policy)
    error = c.receive(Input.SCAN, payload, 0.3)
    assert error is not None and why in error
    assert c.counters.malformed["scan"] == 1
    assert_stop(c.decide(0.5), Reason.SCAN_STALE)


def test_the_scan_plausibility_bounds_are_settings(policy: Path) -> None:
    lidar = LidarSettings(min_readings=10, min_field_of_view_rad=1.0)
    c = Controller(PolicyRuntime(policy), SafetySettings(), lidar)
    assert c.receive(Input.SCAN, scan_layout(count=10, increment=0.1), 0.0) is None
    assert c.receive(Input.SCAN, scan_layout(count=9, increment=0.2), 0.0)
    assert c.receive(Input.SCAN, scan_layout(count=50, increment=0.0199), 0.0)
    assert c.receive(Input.SCAN, scan_layout(count=180, increment=math.pi / 180), 0.0) is None
    assert ready(policy).receive(Input.SCAN, scan_layout(181, math.pi / 180), 0.0) is None


def test_no_malformed_payload_releases_a_latched_stop(policy: Path) -> None:
    rng = np.random.default_rng(11)
    payloads = [bytes.fromhex(h) for h in RELEASE_LOOKALIKES]
    for _ in range(3000):
        size = int(rng.integers(0, 12))
        body = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        payloads.append(b"\x00\x01\x00\x00" + body if rng.random() < 0.7 else body)
    canonical = CANONICAL_TRUE  # written out independently of the reader
    c = ready(policy)
    c.receive(Input.ESTOP, wire.encode_bool_msg(True), 0.0)
    c.receive(Input.ESTOP, wire.encode_bool_msg(False), 0.0)
    for i, payload in enumerate(payloads):
        if payload in canonical:
            continue
        c.receive(Input.ESTOP_RELEASE, payload, 0.001 * i)
        output = c.decide(0.001 * i)
        assert output.command == STOP and output.status.estop_latched, payload.hex()
    # ... and the canonical release still works afterwards.
    c.receive(Input.ESTOP_RELEASE, wire.encode_bool_msg(True), 10.0)
    assert not c.decide(10.0).status.estop_latched


def test_payloads_in_the_wrong_frame_are_malformed_when_a_frame_is_configured(
    policy: Path,
) -> None:
    c = Controller(
        PolicyRuntime(policy), SafetySettings(frame_id="map"), LidarSettings(frame_id="laser")
    )
    assert c.receive(Input.POSE, pose_payload(frame="odom"), 0.0)
    assert c.receive(Input.TARGET, target_payload(frame="odom"), 0.0)
    assert c.receive(Input.SCAN, scan_payload(frame="base_link"), 0.0)
    assert c.counters.malformed == {
        "scan": 1,
        "pose": 1,
        "target": 1,
        "estop": 0,
        "estop_release": 0,
    }
    assert_stop(c.decide(0.0), Reason.NO_SCAN)


def test_a_pose_and_target_in_different_frames_stop_the_car(policy: Path) -> None:
    c = ready(policy)
    c.receive(Input.TARGET, target_payload(frame="odom"), 0.0)
    assert_stop(c.decide(0.01), Reason.FRAME_MISMATCH)


def test_a_scan_of_mostly_invalid_readings_is_refused(policy: Path) -> None:
    c = ready(policy)
    ranges = np.full(720, np.nan, dtype=np.float32)
    ranges[:300] = 3.0
    payload = wire.encode_scan_msg(Scan(0.0, "laser", 0.0, 2 * math.pi / 720, 0.1, 30, ranges))
    assert "invalid" in (c.receive(Input.SCAN, payload, 0.3) or "")
    assert_stop(c.decide(0.5), Reason.SCAN_STALE)


def test_random_bytes_on_every_input_never_move_the_car_nor_raise(policy: Path) -> None:
    rng = np.random.default_rng(7)
    c = controller(policy)
    for step in range(300):
        source = list(Input)[step % len(Input)]
        size = int(rng.integers(0, 200))
        payload = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        if rng.random() < 0.5:  # a valid CDR header and a plausible start
            payload = b"\x00\x01\x00\x00" + payload
        c.receive(source, payload, step * 0.01)
        assert c.decide(step * 0.01).command == STOP
    assert sum(c.counters.malformed.values()) > 250


def test_the_emergency_stop_latches_until_released_after_it_reads_false(policy: Path) -> None:
    c = ready(policy)
    c.receive(Input.ESTOP, wire.encode_bool_msg(True), 0.01)
    assert_stop(c.decide(0.02), Reason.ESTOP_LATCHED)
    assert c.receive(Input.ESTOP_RELEASE, wire.encode_bool_msg(True), 0.03)  # still pressed
    assert c.counters.releases_refused == 1
    c.receive(Input.ESTOP, wire.encode_bool_msg(False), 0.04)
    status = c.decide(0.05).status
    assert status.reason is Reason.ESTOP_LATCHED  # the button is out, but nobody released it
    assert (status.estop_latched, status.estop_pressed) == (True, False)
    c.receive(Input.ESTOP_RELEASE, wire.encode_bool_msg(False), 0.06)  # false asks nothing
    assert_stop(c.decide(0.06), Reason.ESTOP_LATCHED)
    assert c.receive(Input.ESTOP_RELEASE, wire.encode_bool_msg(True), 0.07) is None
    feed(c, 0.07)
    assert c.decide(0.08).status.reason is Reason.POLICY


def test_an_emergency_stop_overrides_every_other_rule(policy: Path) -> None:
    c = controller(policy)
    c.on_estop(True, 0.0)
    assert_stop(c.decide(0.0), Reason.ESTOP_LATCHED)


def test_a_controller_configured_to_start_latched_moves_only_after_a_release(
    policy: Path,
) -> None:
    c = ready(policy, estop_start_latched=True)
    assert_stop(c.decide(0.01), Reason.ESTOP_LATCHED)
    assert c.request_release(0.02) is None
    assert c.decide(0.03).status.reason is Reason.POLICY


def test_after_a_stop_the_policy_starts_a_fresh_window(policy: Path) -> None:
    c = ready(policy)
    first = c.decide(0.01).status.q_values
    c.receive(Input.POSE, pose_payload(x=1.3, yaw=1.0), 0.02)
    second = c.decide(0.03).status.q_values
    assert second != first  # the window now holds two different frames
    c.on_estop(True, 0.04)
    c.on_estop(False, 0.04)
    assert c.decide(0.05).command == STOP
    c.request_release(0.06)
    feed(c, 0.06)
    assert c.decide(0.07).status.q_values == first  # restarted: the same as the first decision


def test_a_pose_that_jumps_starts_a_fresh_window_though_the_target_stays(policy: Path) -> None:
    # A new episode at the same target (BARN's worlds share one goal), or a car carried back to
    # its start: the frames of where it was are no memory of where it is.
    c = ready(policy)
    first = c.decide(0.01).status.q_values
    c.receive(Input.POSE, pose_payload(x=6.0, y=6.0), 0.02)
    assert c.decide(0.03).status.q_values != first
    c.receive(Input.POSE, pose_payload(), 0.04)  # back where it started
    assert c.decide(0.05).status.q_values == first


def test_the_lidarless_policy_decides_on_pose_and_target_alone(make_policy: PolicyFactory) -> None:
    c = controller(make_policy("toycar-inertia"), target_kind="point")
    assert_stop(c.decide(0.0), Reason.NO_POSE)
    c.receive(Input.POSE, pose_payload(), 0.0)
    assert c.receive(Input.TARGET, wire.encode_point_msg(Pose2D(0.0, "map", 4.0, 2.0)), 0.0) is None
    assert c.receive(Input.SCAN, scan_payload(), 0.0) is None  # ignored, not needed
    status = c.decide(0.01).status
    assert status.reason is Reason.POLICY
    assert status.scan_stamp_s is None and status.ages_s["scan"] is None


def test_check_stops_on_the_same_rules_but_never_steps_the_policy(policy: Path) -> None:
    c = ready(policy)
    assert c.check(0.01) is None
    assert c.counters.policy_steps == 0
    assert_stop(c.check(1.0) or c.decide(1.0), Reason.SCAN_STALE)


def test_a_command_sink_gets_each_command_before_its_status_and_changes_nothing(
    policy: Path,
) -> None:
    c, reference = ready(policy), ready(policy)
    sent: list[Twist2D] = []

    def send(command: Twist2D) -> None:
        assert c.counters.decisions == len(sent) + 1  # decided, and its status not yet written
        sent.append(command)

    outputs: list[Output | None] = [c.decide(0.05, send), c.decide(0.1, send)]
    outputs += [c.check(1.0, send), c.shutdown(1.1, send)]
    expected: list[Output | None] = [reference.decide(0.05), reference.decide(0.1)]
    expected += [reference.check(1.0), reference.shutdown(1.1)]
    assert [o.command for o in outputs if o] == sent
    assert [o.status for o in outputs if o] == [o.status for o in expected if o]
    assert sent[0] != STOP and sent[2:] == [STOP, STOP]


def test_the_status_is_one_json_object_with_the_decision_and_its_reasons(policy: Path) -> None:
    c = ready(policy)
    c.note_overruns(2)
    status = c.decide(0.05).status.to_dict()
    decoded = wire.decode_json_msg(wire.encode_json_msg(status))
    assert decoded == json.loads(json.dumps(status))
    assert decoded["reason"] == "policy"
    assert decoded["action"] in ("forward", "left", "right")
    assert decoded["counters"]["overruns"] == 2
    assert set(decoded["ages_s"]) == {i.value for i in Input}
    stop = c.shutdown(0.06).status.to_dict()
    assert stop["reason"] == "shutdown" and stop["q_values"] is None
    wire.encode_json_msg(stop)


@pytest.mark.parametrize(
    ("count", "increment"),
    [(200_000, 1e-5), (60, 4.0), (1000, 0.1), (60, -1e30)],
)
def test_a_scan_that_is_no_planar_scan_is_refused_before_it_is_resampled(
    policy: Path, count: int, increment: float
) -> None:
    c = ready(policy)
    ranges = np.ones(count, dtype=np.float32)
    payload = wire.encode_scan_msg(Scan(0.0, "laser", 0.0, increment, 0.1, 30, ranges))
    assert "not a planar scan" in (c.receive(Input.SCAN, payload, 0.1) or "")
    assert c.counters.malformed["scan"] == 1


@pytest.mark.parametrize("angle_min", [1e30, -1e7, 2 * math.pi + 0.01, -7.0])
def test_a_scan_starting_at_an_absurd_angle_is_refused(policy: Path, angle_min: float) -> None:
    """A finite but absurd angle_min rounds every reading's angle to one: resampled, a scan of
    walls 1 m away all round would read as open space."""
    c = ready(policy)
    ranges = np.full(720, 1.0, dtype=np.float32)
    scan = Scan(0.0, "laser", angle_min, 2 * math.pi / 720, 0.1, 30, ranges)
    assert "angle_min" in (c.receive(Input.SCAN, wire.encode_scan_msg(scan), 0.1) or "")
    assert c.counters.malformed["scan"] == 1
    for start in (-math.pi, 0.0, 2 * math.pi - 0.01):
        scan = Scan(0.0, "laser", start, 2 * math.pi / 720, 0.1, 30, ranges)
        assert c.receive(Input.SCAN, wire.encode_scan_msg(scan), 0.1) is None


def test_a_policy_that_refuses_the_observation_stops_the_car(policy: Path) -> None:
    """The `policy_input_error` rule: a runtime that refuses the observation (here one built
    for two streams, whose single-stream step refuses) stops the car instead of raising."""
    c = Controller(PolicyRuntime(policy, num_streams=2), SafetySettings())
    assert c.receive(Input.TARGET, target_payload(), 0.0) is None
    feed(c, 0.0)
    output = c.decide(0.05)
    assert_stop(output, Reason.POLICY_INPUT_ERROR)
    assert c.counters.policy_steps == 0 and c.counters.stops == 1


def test_a_target_that_only_changes_frame_is_a_new_target(policy: Path) -> None:
    c = ready(policy, target_tolerance_m=0.3)
    c.receive(Input.TARGET, target_payload(1.2, 1.1), 0.0)
    assert_stop(c.decide(0.01), Reason.TARGET_REACHED)
    c.receive(Input.POSE, pose_payload(x=3.0, frame="odom"), 0.02)  # away, in the new frame
    c.receive(Input.TARGET, target_payload(1.2, 1.1, frame="odom"), 0.02)  # same place
    assert c.decide(0.03).status.reason is Reason.POLICY


def test_an_empty_frame_id_on_either_side_skips_the_frame_mismatch_stop(policy: Path) -> None:
    for pose_frame, target_frame in [("", "odom"), ("map", ""), ("", "")]:
        c = controller(policy)
        assert c.receive(Input.TARGET, target_payload(frame=target_frame), 0.0) is None
        feed(c, 0.0, pose=False)
        assert c.receive(Input.POSE, pose_payload(frame=pose_frame), 0.0) is None
        assert c.decide(0.01).status.reason is Reason.POLICY, (pose_frame, target_frame)
    c = controller(policy)
    c.receive(Input.TARGET, target_payload(frame="odom"), 0.0)
    feed(c, 0.0)
    assert_stop(c.decide(0.01), Reason.FRAME_MISMATCH)


def test_the_periodic_check_stops_the_car_when_the_scans_stop(policy: Path) -> None:
    c = ready(policy)
    assert c.check(0.1) is None  # fresh inputs: nothing to stop for, the policy decides on scans
    output = c.check(5.0)
    assert output is not None
    assert_stop(output, Reason.SCAN_STALE)


def test_a_policy_may_be_swapped_in_only_while_the_car_is_stopped_with_no_episode_under_way(
    policy: Path,
) -> None:
    c = controller(policy)
    assert not c.at_rest(0.0)  # nothing decided yet: the car was never told to stop
    feed(c, 0.0)
    assert_stop(c.decide(0.0), Reason.NO_TARGET)
    assert c.at_rest(0.01)
    c.receive(Input.TARGET, target_payload(), 0.01)
    assert not c.at_rest(0.01)  # an episode is about to start
    assert c.decide(0.01).status.reason is Reason.POLICY
    assert not c.at_rest(0.02)
    feed(c, 0.5)
    assert_stop(c.decide(0.5 + 3 * c.period_s), Reason.SCAN_STALE)
    assert not c.at_rest(0.5 + 3 * c.period_s)  # a stale sensor is no rest: it may come back
    c.on_estop(True, 0.6)
    assert_stop(c.decide(0.6), Reason.ESTOP_LATCHED)
    assert c.at_rest(0.6)


def test_a_swapped_policy_decides_from_a_fresh_window_and_names_itself_in_the_status(
    policy: Path, make_policy: PolicyFactory
) -> None:
    other = make_policy("walls-inertia", seed=1)
    c = ready(policy)
    before = c.decide(0.0).status
    assert before.policy_version == delivery.version_of_file(policy)
    c.receive(Input.TARGET, target_payload(1.0, 1.0), 0.01)
    assert_stop(c.decide(0.01), Reason.TARGET_REACHED)
    c.swap_policy(PolicyRuntime(other), "other-1")
    c.receive(Input.TARGET, target_payload(), 0.02)
    feed(c, 0.02)
    after = c.decide(0.02).status
    fresh = ready(other)
    assert after.policy_version == "other-1" and after.counters["policy_swaps"] == 1
    assert after.q_values == pytest.approx(fresh.decide(0.0).status.q_values, abs=1e-6)
    assert after.q_values != pytest.approx(before.q_values, abs=1e-4)


def test_a_policy_that_does_not_keep_the_cars_beams_actions_or_period_is_never_swapped_in(
    policy: Path, make_policy: PolicyFactory
) -> None:
    c = controller(policy)
    with pytest.raises(PolicyFileError, match="beams, control period and actions"):
        c.swap_policy(PolicyRuntime(make_policy("walls-increment")), "increment")
    with pytest.raises(PolicyFileError):
        c.swap_policy(PolicyRuntime(make_policy("toycar-inertia")), "toy")
    assert c.policy_version == delivery.version_of_file(policy)
    assert c.counters.policy_swaps == 0
