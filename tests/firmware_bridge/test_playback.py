"""Playback tests: recorded runs of the bridge fed through a fresh `BridgeCore`.

The recordings (tests/data/bridge_playback, made by tests/data/make_bridge_playback.py from real
runs of the daemon between zenoh and the MAVLink test vehicle) hold every call the daemon made
into its core. Replayed, the core's actions must equal the references kept in the repo (`make
playback-refs` regenerates them on purpose and shows the diff), and equal what the live core
decided (so the recording misses no input). Each recorded fault must get its safe behaviour;
the expectations are read off the recordings themselves (when the commands stop, when the
heartbeats stop), not typed in.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts.mavlink import MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE, mode_number
from qnav.contracts.wire import STOP, WireError, decode_twist_msg
from qnav.firmware_bridge import mapping
from qnav.firmware_bridge.playback import (
    Row,
    call_inputs,
    call_time,
    differences,
    live_references,
    read_recording,
    read_rows,
    replay,
)
from qnav.firmware_bridge.settings import BridgeSettings

DATA = Path(__file__).resolve().parents[1] / "data" / "bridge_playback"
SCENARIOS = ["drive_silence_exit", "malformed", "estop", "heartbeat_loss", "link_loss", "guided"]

Recorded = tuple[BridgeSettings, list[Row]]


@pytest.fixture(scope="module")
def recorded() -> dict[str, Recorded]:
    return {name: read_recording(DATA / f"{name}.recording.jsonl.gz") for name in SCENARIOS}


def _time(call: Row) -> float:
    time_s = call_time(call)
    assert time_s is not None, call
    return time_s


def _sends(call: Row, kind: str | None = None) -> list[Row]:
    return [o for o in call["out"] if "send" in o and (kind is None or o["send"] == kind)]


def _states(calls: list[Row]) -> list[tuple[int, dict[str, Any]]]:
    return [(i, o["state"]) for i, c in enumerate(calls) for o in c["out"] if "state" in o]


def _is_command_long(row: Row, command: int, param: str, value: float) -> bool:
    """Is `row` a COMMAND_LONG `command` with `param` = `value`?"""
    fields = row["fields"]
    return bool(
        row["send"] == "COMMAND_LONG" and fields["command"] == command and fields[param] == value
    )


def _is_mode(row: Row, mode: str) -> bool:
    return _is_command_long(row, MAV_CMD_DO_SET_MODE, "param2", mode_number(mode))


def _is_arming(row: Row, arm: bool) -> bool:
    return _is_command_long(row, MAV_CMD_COMPONENT_ARM_DISARM, "param1", float(arm))


def _neutral(settings: BridgeSettings) -> tuple[int, int]:
    pwm = mapping.rc_override(STOP, settings.output)
    return pwm.steering_pwm_us, pwm.throttle_pwm_us


def _pwm(row: Row) -> tuple[int, int]:
    return row["fields"]["chan1_raw"], row["fields"]["chan3_raw"]


@pytest.mark.parametrize("name", SCENARIOS)
def test_each_recordings_actions_equal_the_references_kept_in_the_repo(
    name: str, recorded: dict[str, Recorded]
) -> None:
    settings, calls = recorded[name]
    changes = differences(read_rows(DATA / f"{name}.actions.jsonl"), replay(settings, calls))
    assert not changes, (
        f"{name}: the bridge's decisions changed; if on purpose, run `make playback-refs` and "
        "commit the new references:\n  " + "\n  ".join(changes)
    )


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_replay_decides_what_the_live_core_decided(
    name: str, recorded: dict[str, Recorded]
) -> None:
    settings, calls = recorded[name]
    assert not differences(live_references(calls), replay(settings, calls))


def test_the_references_can_tell_a_change(recorded: dict[str, Recorded]) -> None:
    settings, calls = recorded["drive_silence_exit"]
    slower = dataclasses.replace(
        settings, failsafe=dataclasses.replace(settings.failsafe, command_timeout_s=0.3)
    )
    reference = read_rows(DATA / "drive_silence_exit.actions.jsonl")
    assert differences(reference, replay(slower, calls))


def test_silence_stops_no_earlier_than_the_timeout_then_brakes_and_a_command_drives_again(
    recorded: dict[str, Recorded],
) -> None:
    settings, calls = recorded["drive_silence_exit"]
    timeout_s = settings.failsafe.command_timeout_s
    last_command_s = -math.inf
    braked_at = None
    for index, call in enumerate(calls):
        if call["event"] == "command":
            if braked_at is not None:
                # The first command after the brake: back to MANUAL, then it drives.
                assert [o["send"] for o in _sends(call)] == ["COMMAND_LONG", "RC_CHANNELS_OVERRIDE"]
                assert _is_mode(_sends(call)[0], "MANUAL")
                assert _pwm(_sends(call)[1]) != _neutral(settings)
                return
            last_command_s = _time(call)
        elif call["event"] == "tick" and last_command_s > -math.inf:
            stops = _sends(call, "RC_CHANNELS_OVERRIDE")
            if stops:
                assert _time(call) - last_command_s >= timeout_s, f"call {index}: stop too early"
                assert all(_pwm(stop) == _neutral(settings) for stop in stops)
                if any(_is_mode(o, "GUIDED") for o in _sends(call)):
                    braked_at = index
    pytest.fail("the recording never braked after silence and drove again")


def test_on_exit_no_command_goes_out_stops_follow_and_the_disarm_waits_for_rest(
    recorded: dict[str, Recorded],
) -> None:
    settings, calls = recorded["drive_silence_exit"]
    refused = next(i for i, c in enumerate(calls) if c["event"] == "refuse_commands")
    shutdown = next(i for i, c in enumerate(calls) if c["event"] == "shutdown")
    after = calls[refused:]
    assert all(not c["out"] for c in after if c["event"] == "command")
    overrides = [o for c in after for o in _sends(c, "RC_CHANNELS_OVERRIDE")]
    assert overrides and all(_pwm(o) == _neutral(settings) for o in overrides)
    first = _sends(calls[shutdown])
    repeats = settings.failsafe.stop_repeats_on_exit
    assert [o["send"] for o in first] == ["RC_CHANNELS_OVERRIDE"] * repeats + ["COMMAND_LONG"]
    assert _is_mode(first[-1], settings.failsafe.brake_mode)
    disarm = next(i for i, c in enumerate(calls) if any(_is_arming(o, False) for o in _sends(c)))
    assert disarm > shutdown
    # The disarm went out only after the vehicle reported a speed under rest_speed_mps.
    speeds = []
    for call in calls[shutdown:disarm]:
        if call["event"] == "exit_message" and "mavlink" in call["args"][0]:
            message = call_inputs(call)[0]
            if message.get_type() == "LOCAL_POSITION_NED":
                speeds.append(math.hypot(message.vx, message.vy))
    assert speeds and speeds[-1] < settings.failsafe.rest_speed_mps
    assert calls[-1]["event"] == "stopped"
    assert calls[-1]["out"][0]["state"]["bridge"] == "stopped"


def test_malformed_payloads_send_nothing_and_absurd_commands_send_a_stop(
    recorded: dict[str, Recorded],
) -> None:
    settings, calls = recorded["malformed"]
    malformed = absurd = 0
    for call in calls:
        if call["event"] == "command":
            payload = call_inputs(call)[0]
            try:
                twist = decode_twist_msg(payload)
            except WireError:
                malformed += 1
                assert call["out"] == []
                continue
            problem = mapping.implausible(
                twist, settings.output, settings.failsafe.implausible_factor
            )
            if problem is not None:
                absurd += 1
                (stop,) = call["out"]
                assert _pwm(stop) == _neutral(settings) and "counts" not in stop
        elif call["event"] in ("pose", "request"):
            assert call["out"] == [], f"a refused {call['event']} sent {call['out']}"
        elif call["event"] == "mavlink" and "bad_data" in call["args"][0]:
            assert call["out"] == []
    assert malformed == 3 and absurd == 3
    arms = [i for i, c in enumerate(calls) for o in _sends(c) if _is_arming(o, True)]
    request = next(i for i, c in enumerate(calls) if c["event"] == "request")
    assert arms and max(arms) < request, "an arm went out after the refused arm request"
    _, last = _states(calls)[-1]
    assert last["counters"]["malformed"] == 9 and last["counters"]["refused"] == 1
    assert last["counters"]["bad_data"] >= 2
    # Garbage changes nothing by itself, and commands after it still drive. (A rogue MAVLink 1
    # header announcing 254 bytes makes the parser swallow the vehicle's next datagrams: in
    # this recording the link dropped for one heartbeat timeout, and the failsafe stopped.)
    garbage = max(
        i for i, c in enumerate(calls) if c["event"] == "mavlink" and "bad_data" in c["args"][0]
    )
    later = [o for c in calls[garbage:] for o in _sends(c, "RC_CHANNELS_OVERRIDE") if "counts" in o]
    assert any(o["counts"] == "commands" and _pwm(o) != _neutral(settings) for o in later)


def test_an_emergency_stop_brakes_at_once_its_zero_commands_going_out_as_neutral(
    recorded: dict[str, Recorded],
) -> None:
    settings, calls = recorded["estop"]
    zeros = [c for c in calls if c["event"] == "command" and _stopping(c)]
    assert len(zeros) >= 5
    for call in zeros:
        assert [o["send"] for o in _sends(call)] == ["RC_CHANNELS_OVERRIDE"]
        assert _pwm(_sends(call)[0]) == _neutral(settings)
    # The controller's zero Twist to a car it was driving is a stop: the brake mode is asked for
    # at once (at the next tick). Its stops keep coming every period, so waiting for silence
    # left the car coasting on neutral sticks for as long as the emergency stop lasted.
    first_zero_s = _time(zeros[0])
    brakes = [c for c in calls if any(_is_mode(o, "GUIDED") for o in _sends(c))]
    assert brakes
    assert first_zero_s <= _time(brakes[0]) < first_zero_s + settings.failsafe.command_timeout_s


def _stopping(call: Row) -> bool:
    twist = decode_twist_msg(call_inputs(call)[0])
    return twist.linear_mps == 0.0 and twist.angular_radps == 0.0


def test_heartbeat_loss_drops_commands_and_motion_waits_for_a_fresh_command(
    recorded: dict[str, Recorded],
) -> None:
    settings, calls = recorded["heartbeat_loss"]
    states = _states(calls)
    down = next(i for i, state in states if state["link_up"] is False and i > 5)
    back = next(i for i, state in states if i > down and state["link_up"] is True)
    timeout_s = settings.mavlink.link_timeout_s
    last_heartbeat_s = max(
        _time(c) for c in calls[:down] if c["event"] == "mavlink" and _from_autopilot(c)
    )
    assert _time(calls[down]) - last_heartbeat_s >= timeout_s
    dropped = [c for c in calls[down:back] if c["event"] == "command"]
    assert len(dropped) >= 4 and all(c["out"] == [] for c in dropped)
    assert any("reopen" in o for c in calls[down:back] for o in c["out"])
    fresh = next(i for i, c in enumerate(calls) if i > back and c["event"] == "command")
    between = [o for c in calls[back:fresh] for o in _sends(c, "RC_CHANNELS_OVERRIDE")]
    assert between, "stops are sent once the link is back"
    assert all(_pwm(o) == _neutral(settings) for o in between)
    assert _pwm(_sends(calls[fresh], "RC_CHANNELS_OVERRIDE")[0]) != _neutral(settings)


def _from_autopilot(call: Row) -> bool:
    if "mavlink" not in call["args"][0]:
        return False
    message = call_inputs(call)[0]
    return bool(message.get_type() == "HEARTBEAT" and message.autopilot != 8)


def test_a_closed_port_is_reopened_every_period_and_arming_waits_for_a_request(
    recorded: dict[str, Recorded],
) -> None:
    settings, calls = recorded["link_loss"]
    reopens = [_time(c) for c in calls if any("reopen" in o for o in c["out"])]
    assert len(reopens) >= 2
    gaps = [b - a for a, b in itertools.pairwise(reopens)]
    assert min(gaps) >= settings.mavlink.reconnect_period_s
    states = _states(calls)
    down = next(i for i, state in states if state["link_up"] is False and i > 5)
    back = next(i for i, state in states if i > down and state["link_up"] is True)
    request = next(i for i, c in enumerate(calls) if c["event"] == "request")
    assert request > back
    arms = [i for i, c in enumerate(calls) for o in _sends(c) if _is_arming(o, True)]
    assert not [i for i in arms if back <= i < request], "armed again without a request"
    assert [i for i in arms if i > request], "the request was not sent"


def test_guided_asks_for_guided_only_after_a_pose_went_out_and_stops_with_a_zero_target(
    recorded: dict[str, Recorded],
) -> None:
    _, calls = recorded["guided"]
    sends = [(i, o) for i, c in enumerate(calls) for o in _sends(c)]
    first_pose = next(i for i, o in sends if o["send"] == "VISION_POSITION_ESTIMATE")
    guided = [i for i, o in sends if _is_mode(o, "GUIDED")]
    assert guided and min(guided) >= first_pose
    assert any(o["send"] == "SET_GPS_GLOBAL_ORIGIN" for _, o in sends)
    targets = [
        (calls[i]["event"], o["fields"])
        for i, o in sends
        if o["send"] == "SET_POSITION_TARGET_LOCAL_NED"
    ]
    driving = [f for event, f in targets if event == "command"]
    stopping = [f for event, f in targets if event in ("tick", "shutdown", "exit_step")]
    assert driving and all(f["vx"] > 0 for f in driving)
    assert stopping and all(f["vx"] == 0.0 and f["yaw_rate"] == 0.0 for f in stopping)
