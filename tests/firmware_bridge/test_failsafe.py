"""The failsafe's decisions on a made-up clock (the daemon runs the same object)."""

from __future__ import annotations

import itertools

from qnav.firmware_bridge.failsafe import CommandGate

TIMEOUT_S, PERIOD_S = 0.5, 0.1


def _gate(link_up: bool = True) -> CommandGate:
    gate = CommandGate(TIMEOUT_S, PERIOD_S)
    gate.set_link(link_up)
    return gate


def _stops(gate: CommandGate, start_s: float, end_s: float, step_s: float = 0.001) -> list[float]:
    """Times at which the daemon's loop would send stop between start and end."""
    sent = []
    for i in range(round((end_s - start_s) / step_s) + 1):
        now = start_s + i * step_s
        if gate.stop_due(now):
            gate.stop_sent(now)
            sent.append(now)
    return sent


def test_stop_is_due_before_any_command() -> None:
    assert _gate().stop_due(0.0)


def test_fresh_command_goes_out_and_suppresses_stop_until_the_timeout() -> None:
    gate = _gate()
    assert gate.accept_command(1.0)
    assert gate.driving(1.0 + TIMEOUT_S - 1e-6)
    assert _stops(gate, 1.0, 1.0 + TIMEOUT_S - 0.001) == []


def test_stale_command_gives_a_stop_at_the_timeout_then_one_every_period() -> None:
    gate = _gate()
    gate.accept_command(1.0)
    stops = _stops(gate, 1.0, 2.0)
    assert abs(stops[0] - (1.0 + TIMEOUT_S)) < 1e-6
    gaps = [b - a for a, b in itertools.pairwise(stops)]
    assert all(abs(gap - PERIOD_S) < 0.0015 for gap in gaps)
    assert len(stops) == 5


def test_stale_command_stops_at_once_even_with_a_long_stop_period() -> None:
    gate = CommandGate(timeout_s=0.5, stop_period_s=2.0)
    gate.set_link(True)
    gate.stop_sent(0.9)
    gate.accept_command(1.0)
    assert gate.stop_due(1.5)


def test_next_check_is_the_moment_the_command_goes_stale() -> None:
    gate = _gate()
    gate.accept_command(1.0)
    assert gate.next_check_s(1.1) == 1.0 + TIMEOUT_S


def test_commands_are_refused_while_the_link_is_down_and_stops_continue() -> None:
    gate = _gate(link_up=False)
    assert not gate.accept_command(1.0)
    assert gate.stop_due(1.0)


def test_link_coming_back_needs_a_fresh_command_before_motion() -> None:
    gate = _gate()
    gate.accept_command(1.0)
    gate.set_link(False)
    gate.set_link(True)
    # The old command is still within its timeout, but it counts for nothing now.
    assert not gate.driving(1.1)
    assert gate.stop_due(1.1)
    assert gate.accept_command(1.2)
    assert gate.driving(1.2)


def test_closed_gate_refuses_every_command() -> None:
    gate = _gate()
    gate.close()
    assert not gate.accept_command(1.0)
    assert gate.stop_due(1.0)


def test_a_fresh_command_does_not_keep_a_closed_gate_driving() -> None:
    gate = _gate()
    assert gate.accept_command(1.0)
    assert gate.driving(1.1)
    gate.close()
    assert not gate.driving(1.1)  # still fresh, but the bridge is shutting down
    assert gate.stop_due(1.1)
