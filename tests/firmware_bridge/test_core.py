"""The bridge's core on its own: no clock, no socket, no thread; time is an argument."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Any

from qnav.contracts.mavlink import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_MODE_FLAG_SAFETY_ARMED,
    mavutil,
)
from qnav.contracts.settings import with_overrides
from qnav.contracts.wire import STOP, Twist2D, encode_twist_msg
from qnav.firmware_bridge import mapping
from qnav.firmware_bridge.core import BridgeCore, Send
from qnav.firmware_bridge.settings import BridgeSettings

CORE = Path(__file__).resolve().parents[2] / "firmware_bridge" / "core.py"


def _heartbeat(armed: bool = True) -> Any:
    """The autopilot's HEARTBEAT (system 1, component 1) as the port would hand it over."""
    mav = mavutil().mavlink
    sender = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    flags = MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
    packed = sender.heartbeat_encode(10, 3, flags, 0, 4).pack(sender)
    return mav.MAVLink(None).decode(bytearray(packed))


def _overrides(actions: list[Any]) -> list[tuple[int, int]]:
    return [
        (a.message.chan1_raw, a.message.chan3_raw)
        for a in actions
        if isinstance(a, Send) and a.message.get_type() == "RC_CHANNELS_OVERRIDE"
    ]


def test_the_core_imports_no_clock_socket_thread_or_transport() -> None:
    names: set[str] = set()
    for node in ast.walk(ast.parse(CORE.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    io = {
        "time",
        "socket",
        "threading",
        "zenoh",
        "qnav.contracts.transport",
        "qnav.firmware_bridge.link",
    }
    assert not names & io


def test_a_command_goes_out_only_with_the_link_up_and_silence_stops_at_the_timeout() -> None:
    settings = BridgeSettings()
    core = BridgeCore(settings)
    forward = encode_twist_msg(Twist2D(0.5, 0.0))
    assert core.command(forward, 10.0) == []  # no heartbeat yet: dropped
    assert core.counters["dropped"] == 1
    core.mavlink(_heartbeat(), 10.1, 0.0)
    assert core.link_up and core.armed
    sent = core.command(forward, 10.2)
    moving = mapping.rc_override(Twist2D(0.5, 0.0), settings.output)
    assert _overrides(sent) == [(moving.steering_pwm_us, moving.throttle_pwm_us)]
    timeout_s = settings.failsafe.command_timeout_s
    assert _overrides(core.tick(10.2 + timeout_s - 0.01, 0.0, True)) == []
    neutral = mapping.rc_override(STOP, settings.output)
    stop = (neutral.steering_pwm_us, neutral.throttle_pwm_us)
    assert _overrides(core.tick(10.2 + timeout_s, 0.0, True)) == [stop]
    assert core.next_deadline(10.2 + timeout_s, True) <= 10.2 + timeout_s + 0.1


def test_the_same_inputs_give_the_same_actions() -> None:
    def run() -> list[Any]:
        core = BridgeCore(BridgeSettings())
        out = core.mavlink(_heartbeat(), 1.0, 100.0) + core.tick(1.0, 100.0, True)
        out += core.command(encode_twist_msg(Twist2D(0.3, 0.2)), 1.05)
        out += core.tick(2.0, 101.0, True) + core.shutdown(2.1)
        return [a.message.to_dict() if isinstance(a, Send) else a for a in out]

    assert run() == run()


def _speed_report(speed_mps: float) -> Any:
    """The autopilot's LOCAL_POSITION_NED moving north at `speed_mps`."""
    mav = mavutil().mavlink
    sender = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    packed = sender.local_position_ned_encode(0, 0.0, 0.0, 0.0, speed_mps, 0.0, 0.0).pack(sender)
    return mav.MAVLink(None).decode(bytearray(packed))


def _disarmed_at(core: BridgeCore, speed_at: Any, start_s: float, end_s: float) -> float | None:
    """Run the exit sequence from `start_s`, the vehicle reporting `speed_at(t)` every 0.1 s
    (and acknowledging nothing); the time of the first disarm, None if none before `end_s`."""
    now = start_s
    core.shutdown(now)
    while now < end_s:
        core.exit_message(_speed_report(speed_at(now - start_s)), now, 0.0)
        for action in core.exit_step(now):
            if (
                isinstance(action, Send)
                and action.message.get_type() == "COMMAND_LONG"
                and action.message.command == MAV_CMD_COMPONENT_ARM_DISARM
            ):
                return now - start_s
        if core.exit_wait_until_s is None:
            return None
        now = round(now + 0.1, 6)
    return None


def _exiting_core(**failsafe: float) -> BridgeCore:
    core = BridgeCore(with_overrides(BridgeSettings(), {"failsafe": failsafe}))
    core.mavlink(_heartbeat(), 0.0, 0.0)
    return core


def test_exit_holds_the_brake_while_the_car_slows_and_disarms_it_at_rest() -> None:
    # Issue 53: in SITL the bridge disarmed 5 s (rest_timeout_s) after its stop while the car
    # still rolled at 0.5-1 m/s. A car slowing from 2 m/s at 0.2 m/s/s is at rest after 10 s.
    core = _exiting_core(rest_timeout_s=2.0)
    disarmed = _disarmed_at(core, lambda t: max(0.0, 2.0 - 0.2 * t), 10.0, 60.0)
    assert disarmed is not None and 9.7 <= disarmed <= 10.3


def test_exit_disarms_a_car_that_does_not_slow_after_rest_timeout_s() -> None:
    # Its brakes do nothing (or something else drives it): disarming loses nothing.
    core = _exiting_core(rest_timeout_s=2.0)
    disarmed = _disarmed_at(core, lambda t: 1.0, 10.0, 60.0)
    assert disarmed is not None and 1.9 <= disarmed <= 2.2


def test_exit_disarms_a_car_still_slowing_after_brake_timeout_s() -> None:
    core = _exiting_core(rest_timeout_s=2.0, brake_timeout_s=8.0)
    disarmed = _disarmed_at(core, lambda t: max(0.0, 3.0 - 0.2 * t), 10.0, 60.0)
    assert disarmed is not None and 7.9 <= disarmed <= 8.2
