"""The bridge against ArduPilot Rover SITL: arming, motion, turning, every stop and fault.

Real parts only: the `ardurover` binary (ARDUPILOT_SITL), `qnav bridge` as a process, a zenoh
peer on loopback. Motion and stops are measured from the autopilot's own LOCAL_POSITION_NED
(and GLOBAL_POSITION_INT), read by an observer on SERIAL0. `pytest -s` prints each stop's
figures (docs/bridge-testing.md, "Measured stops", comes from them).

Each bridge is started while the autopilot still boots (its EKF waits for GPS and a settled
IMU, tens of seconds): that is the cold start, and arming must wait for it.
"""

from __future__ import annotations

import math
import signal
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from qnav.contracts.mavlink import signing_timestamp_now, wrap_pi
from qnav.contracts.settings import from_dict
from qnav.firmware_bridge.calibrate import Calibrator, Pattern
from qnav.firmware_bridge.settings import BridgeSettings
from qnav.sitl import HOME
from tests.firmware_bridge.rig import wait_until
from tests.sitl.harness import (
    EKF_CONST_POS_MODE,
    EKF_POS_HORIZ_ABS,
    BridgeProcess,
    LinkCutter,
    MotionCapture,
    Observer,
    Sitl,
    StopMeasure,
    Zenoh,
    measure_stop,
    true_pose,
)

pytestmark = pytest.mark.sitl

StartSitl = Callable[..., tuple[Sitl, Observer]]
StartBridge = Callable[..., BridgeProcess]

ROOT = Path(__file__).resolve().parents[2]
BOOT_TIMEOUT_S = 150.0
"""SITL's EKF needs GPS and a settled IMU before it may arm: tens of seconds after boot."""
DRIVE_SPEED_MPS = 1.0
"""The toy car's top speed in the paper's use (the policy's largest forward command)."""
SITL_FULL_THROTTLE_MPS = 20.0
"""SITL's rover at full throttle in MANUAL (SIM_Rover: 20 m/s; `qnav calibrate-car` finds it)."""
STOP_GOAL_S = 1.5
"""At rest within this long of silence or SIGTERM (issue 20)."""
FAILSAFE_GOAL_S = 2.0
"""At rest within this long of a SIGKILL of the bridge, by the autopilot's own failsafe."""

OUTPUTS = {
    "manual-neutral": [
        'output.mode="manual"',
        f"output.speed_at_full_throttle_mps={SITL_FULL_THROTTLE_MPS}",
        'failsafe.brake_mode=""',
    ],
    "manual-brake": [
        'output.mode="manual"',
        f"output.speed_at_full_throttle_mps={SITL_FULL_THROTTLE_MPS}",
        'failsafe.brake_mode="GUIDED"',
    ],
    "guided": ['output.mode="guided"', "vision.forward_pose=false"],
}
"""Bridge settings per case (guided with GPS here: SITL's EKF has its own position)."""


def _report(what: str, measure: StopMeasure) -> None:
    print(
        f"\n[sitl] {what}: from {measure.speed_before_mps:.2f} m/s, at rest after "
        f"{measure.stop_time_s:.2f} s, {measure.stop_distance_m:.2f} m "
        f"(GLOBAL_POSITION_INT: {measure.gps_distance_m:.2f} m); truly at rest after "
        f"{measure.true_stop_time_s:.2f} s (SIM_STATE; the EKF's velocity then "
        f"{measure.ekf_error_mps:.3f} m/s off)"
    )


def _armed(zenoh: Zenoh, observer: Observer, timeout_s: float = BOOT_TIMEOUT_S) -> None:
    wait_until(
        lambda: (
            zenoh.state().get("armed")
            and zenoh.state().get("bridge") == "running"
            and observer.armed
        ),
        timeout_s,
        "the bridge to arm the rover",
    )


def _forward_m(observer: Observer, start: tuple[float, float], yaw_ned: float) -> float:
    north, east = observer.position()
    return (north - start[0]) * math.cos(yaw_ned) + (east - start[1]) * math.sin(yaw_ned)


def _drive_and_check_motion(zenoh: Zenoh, observer: Observer) -> float:
    """Forward, then a left turn; the time of the last command."""
    wait_until(lambda: observer.latest("ATTITUDE"), 30, "ATTITUDE")
    start, yaw0 = observer.position(), observer.yaw_ned()
    zenoh.drive(DRIVE_SPEED_MPS, 0.0, 4.0)
    travelled = _forward_m(observer, start, yaw0)
    assert travelled > 1.5, (
        f"moved {travelled:.2f} m forward in 4 s at {DRIVE_SPEED_MPS} m/s; "
        f"modes {[(round(t - time.monotonic(), 2), m) for t, _, m in observer.changes[-4:]]}; "
        f"texts {observer.texts[-6:]}"
    )
    speed = observer.speed()
    assert 0.5 * DRIVE_SPEED_MPS < speed < 2.0 * DRIVE_SPEED_MPS, f"speed {speed:.2f} m/s"
    # angular.z > 0 turns counter-clockwise seen from above: the NED yaw decreases.
    yaw1 = observer.yaw_ned()
    last = zenoh.drive(DRIVE_SPEED_MPS, 0.5, 2.0)
    turned = wrap_pi(observer.yaw_ned() - yaw1)
    assert turned < -0.3, f"NED yaw changed by {turned:.2f} rad on a left turn"
    return last


@pytest.mark.parametrize("case", list(OUTPUTS))
def test_drive_and_every_stop(
    case: str, start_sitl: StartSitl, start_bridge: StartBridge, zenoh: Zenoh
) -> None:
    sitl, observer = start_sitl()
    bridge = start_bridge(sitl.serial1, *OUTPUTS[case])
    # Cold start: the bridge came up while the autopilot booted; it must keep asking.
    _armed(zenoh, observer)
    assert "giving up" not in bridge.log()
    # Neutral sticks in MANUAL coast: measured, no goal. Every braking stop is held to the goal
    # by the car's true velocity (SITL's SIM_STATE), and by the EKF's estimate of it too except
    # guided's silence stop, the first stop after boot: there the EKF's velocity is still off by
    # 0.05-0.08 m/s after braking (its yaw is 1.5-2 degrees off), about the rest speed, and it
    # reports rest some 0.7 s after the car is at rest (docs/bridge-testing.md, "Measured stops").
    goal = case.endswith("brake")
    exit_goal = case != "manual-neutral"
    if exit_goal:  # braking in GUIDED needs the EKF's position: GPS, some 20 s after boot
        wait_until(
            lambda: any("is using GPS" in text for text in observer.texts),
            BOOT_TIMEOUT_S,
            "the EKF using GPS",
        )
    if case.startswith("guided"):
        wait_until(lambda: observer.mode == "GUIDED", BOOT_TIMEOUT_S, "GUIDED")

    # 1. Command silence: the bridge's own failsafe.
    last = _drive_and_check_motion(zenoh, observer)
    silence = measure_stop(observer, last, timeout_s=30.0)
    _report(f"{case}, command silence", silence)
    assert silence.rested
    if goal:
        assert silence.stop_time_s <= STOP_GOAL_S + 0.5  # + the 0.5 s command timeout
    if exit_goal:
        assert silence.true_stop_time_s <= STOP_GOAL_S + 0.5

    # 1b. The controller's own stop (an emergency stop, a stale input): zero Twists every period,
    # so the commands never fall silent. The bridge brakes on the first one after motion.
    _drive_and_check_motion(zenoh, observer)
    zeros = threading.Thread(target=zenoh.drive, args=(0.0, 0.0, 8.0))
    first_zero_s = time.monotonic()
    zeros.start()
    held = measure_stop(observer, first_zero_s, timeout_s=30.0)
    zeros.join()
    _report(f"{case}, the controller's zero Twists", held)
    assert held.rested
    if exit_goal:  # the brake mode, or guided's zero velocity target (issue 53: not asserted)
        assert held.true_stop_time_s <= STOP_GOAL_S

    # 2. SIGTERM while driving: stop, brake, disarm only once at rest.
    _drive_and_check_motion(zenoh, observer)
    sent = bridge.signal(signal.SIGTERM)
    term = measure_stop(observer, sent, timeout_s=30.0)
    _report(f"{case}, SIGTERM", term)
    assert bridge.wait(timeout_s=15.0) == 0
    assert term.rested
    if exit_goal:
        assert term.stop_time_s <= STOP_GOAL_S
        assert term.true_stop_time_s <= STOP_GOAL_S
    wait_until(lambda: observer.armed is False, 5.0, "the disarm on exit")
    disarmed_s = next(t for t, armed, _ in reversed(observer.changes) if not armed)
    assert disarmed_s >= sent + term.stop_time_s - 1.0, "disarmed while still moving"

    # 3. SIGKILL while driving: nothing from the bridge any more; the autopilot's own
    # failsafe (FS_GCS_*, FS_ACTION, config/ardupilot-sitl.parm) must stop the car.
    bridge = start_bridge(sitl.serial1, *OUTPUTS[case])
    _armed(zenoh, observer, timeout_s=30.0)
    wait_until(
        lambda: observer.mode == ("GUIDED" if case.startswith("guided") else "MANUAL"),
        10.0,
        "the output's mode",
    )
    _drive_and_check_motion(zenoh, observer)
    killed = bridge.signal(signal.SIGKILL)
    kill = measure_stop(observer, killed, timeout_s=30.0)
    _report(f"{case}, SIGKILL", kill)
    print(f"[sitl] {case}: modes after SIGKILL: {observer.changes[-3:]}")
    assert kill.rested
    assert kill.stop_time_s <= FAILSAFE_GOAL_S
    assert kill.true_stop_time_s <= FAILSAFE_GOAL_S


def test_signing_on_a_telemetry_port_refuses_unsigned_and_wrongly_signed_senders(
    start_sitl: StartSitl, start_bridge: StartBridge, zenoh: Zenoh, tmp_path: Path
) -> None:
    sitl, observer = start_sitl()
    key = bytes(range(32))
    key_file = tmp_path / "signing.key"
    key_file.write_text(key.hex())
    key_file.chmod(0o600)
    wrong_file = tmp_path / "wrong.key"
    wrong_file.write_text(bytes(range(1, 33)).hex())
    wrong_file.chmod(0o600)
    # The key goes to the autopilot over SERIAL0, as MAVProxy's `signing setup` over USB.
    # Its timestamp in MAVLink's units (10 us since 2015): a later one would make the
    # autopilot refuse every packet stamped now as a replay.
    observer.send(lambda mav: mav.setup_signing_send(1, 1, key, signing_timestamp_now()))
    wait_until(lambda: observer.latest("ATTITUDE"), 30, "telemetry")

    # A bridge with the wrong key never hears a signed autopilot: no link, no arming.
    wrong = start_bridge(sitl.serial1, "signing.enabled=true", f'signing.key_file="{wrong_file}"')
    time.sleep(20.0)
    assert not zenoh.state().get("link_up")
    assert observer.armed is False
    assert wrong.signal(signal.SIGTERM) and wrong.wait() == 0

    # An unsigned bridge on the same port: its arm requests are dropped.
    unsigned = start_bridge(sitl.serial1)
    time.sleep(10.0)
    assert observer.armed is False
    unsigned.signal(signal.SIGTERM)
    unsigned.wait()

    # The right key: link, arming, motion.
    right = start_bridge(sitl.serial1, "signing.enabled=true", f'signing.key_file="{key_file}"')
    _armed(zenoh, observer)
    start, yaw = observer.position(), observer.yaw_ned()
    zenoh.drive(DRIVE_SPEED_MPS, 0.0, 3.0)
    assert _forward_m(observer, start, yaw) > 1.0
    assert "SIGNING PROTECTS NOTHING" not in right.log()


MOCAP_OUTPUTS = {
    "guided": ['output.mode="guided"'],
    "manual": [
        'output.mode="manual"',
        f"output.speed_at_full_throttle_mps={SITL_FULL_THROTTLE_MPS}",
        'failsafe.brake_mode="GUIDED"',
    ],
}
"""Bridge settings per output on a mocap-only autopilot (the pose forwarded in both)."""


def _mocap_position(observer: Observer, mode: str, since_s: float) -> None:
    """Wait for the output's mode and for the EKF to take the forwarded pose as its position."""
    wait_until(lambda: observer.mode == mode, BOOT_TIMEOUT_S, f"{mode} on the mocap pose")

    # Without a position the brake mode (GUIDED) is refused and FS_ACTION 6 falls back to
    # Hold, which coasts: only with the pose as the EKF's position can either brake.
    # After a link loss the poses stopped with it: the EKF's position drifted ("EKF variance",
    # "EKF failsafe") and converges back when they return, which moves LOCAL_POSITION_NED
    # (the drive's measure) on its own: wait until it is healthy again (variances below half
    # of Rover's FS_EKF_THRESH 0.8, not in constant-position mode) for a second, and agrees
    # with the true pose (SIMSTATE, what the motion capture publishes) within 0.1 m and 0.05
    # rad (the drive is measured along the EKF's heading).
    home = (float(HOME.split(",")[0]), float(HOME.split(",")[1]))

    def healthy() -> bool:
        reports = observer.since("EKF_STATUS_REPORT", since_s)
        recent = [r for r in reports if r.time_s > time.monotonic() - 1.0]
        truth = observer.latest("SIMSTATE")
        if len(recent) < 2 or truth is None or recent[0].time_s - reports[0].time_s < 1.0:
            return False
        east, north, _ = true_pose(truth.fields, home)
        estimate = observer.position()
        yaw_error = wrap_pi(observer.yaw_ned() - float(truth.fields["yaw"]))
        close = math.hypot(estimate[0] - north, estimate[1] - east) < 0.1
        return (
            close
            and abs(yaw_error) < 0.05
            and all(
                int(r.fields["flags"]) & EKF_POS_HORIZ_ABS
                and not int(r.fields["flags"]) & EKF_CONST_POS_MODE
                and r.fields["pos_horiz_variance"] < 0.4
                and r.fields["velocity_variance"] < 0.4
                for r in recent
            )
        )

    wait_until(healthy, BOOT_TIMEOUT_S, "the EKF's position from the motion-capture pose")


@pytest.mark.parametrize("output", list(MOCAP_OUTPUTS))
def test_mocap_only_drives_and_stops(
    output: str, start_sitl: StartSitl, start_bridge: StartBridge, zenoh: Zenoh, tmp_path: Path
) -> None:
    # Indoors: no GPS (SITL's simulated receiver off too), no compass; the EKF's position and
    # yaw come only from the pose the bridge forwards (config/ardupilot-mocap.parm), in the
    # manual output as in guided.
    no_gps = tmp_path / "no-gps.parm"
    no_gps.write_text("SIM_GPS1_ENABLE 0\n")
    sitl, observer = start_sitl([ROOT / "config" / "ardupilot-mocap.parm", no_gps])
    mocap = MotionCapture(zenoh, observer)
    try:
        bridge = start_bridge(sitl.serial1, *MOCAP_OUTPUTS[output])
        _armed(zenoh, observer)
        _mocap_position(observer, output.upper(), 0.0)
        assert observer.since("GLOBAL_POSITION_INT", 0.0), "the EKF has a position"
        last = _drive_and_check_motion(zenoh, observer)
        silence = measure_stop(observer, last, timeout_s=30.0)
        _report(f"mocap-only {output}, command silence", silence)
        assert silence.rested and silence.stop_time_s <= STOP_GOAL_S + 0.5
        assert mocap.published > 100
        assert zenoh.state()["counters"]["poses"] > 100
        assert "giving up" not in bridge.log()
        # SIGTERM while driving: stop, brake, disarm once at rest (SIGKILL and link loss:
        # test_the_autopilots_own_failsafe_stops_the_car_after_sigkill_and_link_loss).
        _drive_and_check_motion(zenoh, observer)
        sent = bridge.signal(signal.SIGTERM)
        term = measure_stop(observer, sent, timeout_s=30.0)
        _report(f"mocap-only {output}, SIGTERM", term)
        assert bridge.wait(timeout_s=15.0) == 0
        assert term.rested and term.stop_time_s <= STOP_GOAL_S
        wait_until(lambda: observer.armed is False, 5.0, "the disarm on exit")
    finally:
        mocap.close()


def test_calibrate_car_makes_a_twist_drive_at_the_speed_it_asks(
    start_sitl: StartSitl, start_bridge: StartBridge, zenoh: Zenoh
) -> None:
    # A wrong scale (1 m/s at full throttle: a 0.5 m/s Twist is half throttle, many m/s in
    # SITL), then `qnav calibrate-car`'s pattern, then the fitted scale.
    sitl, observer = start_sitl()
    wrong = ['output.mode="manual"', "output.speed_at_full_throttle_mps=1.0"]
    bridge = start_bridge(sitl.serial1, *wrong)
    _armed(zenoh, observer)
    settings = from_dict(
        BridgeSettings,
        {
            "zenoh": {"connect": [f"tcp/127.0.0.1:{zenoh.port}"]},
            "output": {"speed_at_full_throttle_mps": 1.0},
        },
    )
    # SITL's rover: 20 m/s at full throttle, reached with a 2 s time constant.
    pattern = Pattern(
        throttle_fractions=(0.03, 0.05, 0.08),
        steering_fractions=(0.5,),
        turn_throttle_fraction=0.05,
        settle_s=6.0,
        rest_timeout_s=20.0,
        max_distance_m=150.0,
    )
    calibrator = Calibrator(settings, pattern)
    try:
        calibrator.wait_ready(30.0)
        result = calibrator.calibrate()
    finally:
        calibrator.close()
    speed_scale = result["speed_at_full_throttle_mps"]
    turn_scale = result["turn_rate_at_full_steering_radps"]
    print(f"\n[sitl] calibrate-car: {speed_scale:.2f} m/s, {turn_scale:.2f} rad/s at full travel")
    for run in result["runs"]:
        print(f"[sitl]   {run}")
    bridge.signal(signal.SIGTERM)
    bridge.wait(timeout_s=15.0)
    calibrated = start_bridge(
        sitl.serial1,
        'output.mode="manual"',
        f"output.speed_at_full_throttle_mps={speed_scale}",
        f"output.turn_rate_at_full_steering_radps={turn_scale}",
    )
    _armed(zenoh, observer, timeout_s=30.0)
    zenoh.drive(DRIVE_SPEED_MPS, 0.0, 8.0)  # SITL's rover reaches speed with a 2 s lag
    speed = observer.speed()
    print(f"[sitl] a {DRIVE_SPEED_MPS} m/s Twist after calibration: {speed:.2f} m/s")
    assert speed == pytest.approx(DRIVE_SPEED_MPS, rel=0.2)
    assert calibrated.process.poll() is None


FAULT_REPEATS = 3
"""Each fault is measured this many times per configuration: the goal holds for the worst."""
FAULT_CASES = {
    "manual": (OUTPUTS["manual-neutral"], False),
    "guided": (OUTPUTS["guided"], False),
    "mocap-guided": (MOCAP_OUTPUTS["guided"], True),
    "mocap-manual": (MOCAP_OUTPUTS["manual"], True),
}
"""Bridge settings, and whether the autopilot runs mocap-only (config/ardupilot-mocap.parm)."""


@pytest.mark.parametrize("case", list(FAULT_CASES))
def test_the_autopilots_own_failsafe_stops_the_car_after_sigkill_and_link_loss(
    case: str, start_sitl: StartSitl, start_bridge: StartBridge, zenoh: Zenoh, tmp_path: Path
) -> None:
    # Nothing from the bridge reaches the autopilot any more, either because the bridge died
    # without a word (SIGKILL) or because the link went silent with the bridge alive (a relay
    # that stops passing bytes, both ways, sockets open: a radio out of range). Only the
    # autopilot's GCS failsafe (FS_GCS_TIMEOUT, FS_TIMEOUT, FS_ACTION; config/ardupilot-sitl.parm)
    # can stop the car. Goal: at rest within 2 s, for the worst of the repeats.
    assignments, mocap_only = FAULT_CASES[case]
    extra = []
    if mocap_only:
        no_gps = tmp_path / "no-gps.parm"
        no_gps.write_text("SIM_GPS1_ENABLE 0\n")
        extra = [ROOT / "config" / "ardupilot-mocap.parm", no_gps]
    sitl, observer = start_sitl(extra)
    mocap = MotionCapture(zenoh, observer) if mocap_only else None
    mode = "GUIDED" if case.endswith("guided") else "MANUAL"
    measures: dict[str, list[StopMeasure]] = {"SIGKILL": [], "link loss": []}
    try:
        for fault in [*measures] * FAULT_REPEATS:
            relay = LinkCutter(sitl.base_port + 2) if fault == "link loss" else None
            started_s = time.monotonic()
            bridge = start_bridge(relay.connection if relay else sitl.serial1, *assignments)
            _armed(zenoh, observer)
            wait_until(
                lambda: observer.mode == mode and zenoh.state().get("link_up"),
                BOOT_TIMEOUT_S,
                mode,
            )
            if mocap_only:
                _mocap_position(observer, mode, started_s)
            else:
                # FS_ACTION 6 is Loiter only with the EKF's position (GPS here, some 20 s after
                # boot); without one it is Hold, which coasts: 6.6 s, 2.4 m in manual, seen.
                wait_until(
                    lambda: any("is using GPS" in t for t in observer.texts), BOOT_TIMEOUT_S, "GPS"
                )
            _drive_and_check_motion(zenoh, observer)
            event = bridge.signal(signal.SIGKILL) if relay is None else relay.cut()
            measure = measure_stop(observer, event, timeout_s=30.0)
            measures[fault].append(measure)
            _report(f"{case}, {fault}", measure)
            switched = [(round(t - event, 2), m) for t, _, m in observer.changes if t > event]
            trace = [
                (round(x.time_s - event, 2), round(math.hypot(x.fields["vx"], x.fields["vy"]), 3))
                for x in observer.since("LOCAL_POSITION_NED", event)[::4]
            ][:16]
            print(f"[sitl] {case}, {fault}: modes after it {switched}; speeds {trace}")
            if relay is not None:
                bridge.signal(signal.SIGTERM)
                bridge.wait(timeout_s=20.0)
                relay.close()
            else:
                bridge.wait(timeout_s=5.0)
    finally:
        if mocap is not None:
            mocap.close()
    for fault, runs in measures.items():
        times = sorted(m.stop_time_s for m in runs)
        true_times = sorted(m.true_stop_time_s for m in runs)
        print(
            f"[sitl] {case}, {fault}: at rest after median {statistics.median(times):.2f} s, "
            f"worst {times[-1]:.2f} s, over {len(times)} (distances "
            f"{', '.join(f'{m.stop_distance_m:.2f}' for m in runs)} m); truly at rest after "
            f"median {statistics.median(true_times):.2f} s, worst {true_times[-1]:.2f} s"
        )
        assert all(m.rested for m in runs)
        # The goal is the car's rest, held by SITL's true velocity (on the car: motion capture).
        # The EKF's own figure is printed, not held: after the first hard stop after boot its
        # yaw is 1.5-2 degrees off and its velocity 0.05-0.08 m/s wrong, right at the rest
        # threshold, so it reads "moving" for up to 0.8 s after the car stopped (tests/sitl/
        # trace_stops.py; docs/bridge-testing.md, "Measured stops").
        assert all(t <= FAILSAFE_GOAL_S for t in true_times), f"{case}, {fault}: {true_times}"
