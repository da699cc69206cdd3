"""Property: no malformed payload on any key the controller subscribes to can release the
emergency stop or move the car, through the controller's real decision path
(`Controller.receive`, then `decide`), with payloads from tests/contracts/malformed.py.

For each key the controller starts in the states where that key's input is what keeps the car
stopped: the input missing or stale (scan, pose, target), the stop latched with the button out
(release), or driving (estop, where a malformed payload must press the stop). Each payload must
be refused and counted, and the output must be the same stop as before it.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from qnav.contracts import wire
from qnav.contracts.wire import STOP, Pose2D
from qnav.controller.config import SafetySettings
from qnav.controller.decision import Controller, Input, Reason
from qnav.controller.policy import PolicyRuntime
from tests.conftest import PolicyFactory
from tests.contracts.malformed import malformed
from tests.controller.test_decision import pose_payload, scan_payload, target_payload

MESSAGE_OF = {
    Input.SCAN: "scan",
    Input.POSE: "pose",
    Input.TARGET: "pose",
    Input.ESTOP: "bool",
    Input.ESTOP_RELEASE: "bool",
}
"""The message each key carries (targets: PoseStamped, the default target kind)."""

CASES_PER_KEY = 400
"""Payloads per key in the default suite (the slow variant sends 10,000 and 10 MB ones)."""


@pytest.fixture
def policy(make_policy: PolicyFactory) -> Path:
    return make_policy("walls-inertia")


def _fed(runtime: PolicyRuntime, now: float, *, skip: Input | None = None) -> Controller:
    c = Controller(runtime, SafetySettings())
    if skip is not Input.TARGET:
        assert c.receive(Input.TARGET, target_payload(), now) is None
    if skip is not Input.SCAN:
        assert c.receive(Input.SCAN, scan_payload(now), now) is None
    if skip is not Input.POSE:
        assert c.receive(Input.POSE, pose_payload(), now) is None
    return c


def _starting_states(runtime: PolicyRuntime, key: Input) -> list[tuple[Controller, Reason, float]]:
    """(controller, the stop it is in, the time to decide at) for one key."""
    if key in (Input.SCAN, Input.POSE, Input.TARGET):
        missing = {Input.SCAN: Reason.NO_SCAN, Input.POSE: Reason.NO_POSE}
        states = [(_fed(runtime, 0.0, skip=key), missing.get(key, Reason.NO_TARGET), 0.05)]
        if key is not Input.TARGET:  # stale: fed at 0, deciding a second later with the rest fresh
            c = _fed(runtime, 0.0)
            for other in (Input.SCAN, Input.POSE):
                if other is not key:
                    payload = scan_payload(1.0) if other is Input.SCAN else pose_payload()
                    assert c.receive(other, payload, 1.0) is None
            stale = Reason.SCAN_STALE if key is Input.SCAN else Reason.POSE_STALE
            states.append((c, stale, 1.0))
        return states
    c = _fed(runtime, 0.0)
    if key is Input.ESTOP_RELEASE:  # latched, the button out: one canonical true would release
        c.receive(Input.ESTOP, wire.encode_bool_msg(True), 0.0)
        c.receive(Input.ESTOP, wire.encode_bool_msg(False), 0.0)
    return [(c, Reason.ESTOP_LATCHED, 0.05)]


def check_no_malformed_payload_releases_or_moves(
    runtime: PolicyRuntime, key: Input, count: int, seed: int, max_bytes: int
) -> Counter[str]:
    kinds: Counter[str] = Counter()
    rng = np.random.default_rng(seed)
    states = _starting_states(runtime, key)
    for index, (kind, payload) in enumerate(malformed(MESSAGE_OF[key], rng, count, max_bytes)):
        c, reason, now = states[index % len(states)]
        refused_before = c.counters.malformed[key.value]
        error = c.receive(key, payload, now)
        assert error is not None, (key, kind, payload[:80].hex())
        assert c.counters.malformed[key.value] == refused_before + 1
        output = c.decide(now)
        assert output.command == STOP, (key, kind, payload[:80].hex())
        assert output.status.reason is reason, (key, kind, output.status.reason)
        assert c.estop_latched == (reason is Reason.ESTOP_LATCHED)
        kinds[kind] += 1
    return kinds


@pytest.mark.parametrize("key", list(Input))
def test_no_malformed_payload_on_any_key_releases_or_moves(policy: Path, key: Input) -> None:
    kinds = check_no_malformed_payload_releases_or_moves(
        PolicyRuntime(policy), key, CASES_PER_KEY, seed=18, max_bytes=1 << 20
    )
    assert sum(kinds.values()) > CASES_PER_KEY and len(kinds) >= 10, kinds


def test_a_malformed_estop_payload_presses_a_driving_car_to_a_stop(policy: Path) -> None:
    rng = np.random.default_rng(19)
    runtime = PolicyRuntime(policy)
    for kind, payload in malformed("bool", rng, 100, max_bytes=0):
        c = _fed(runtime, 0.0)
        assert c.decide(0.01).status.reason is Reason.POLICY
        assert c.receive(Input.ESTOP, payload, 0.02), kind
        output = c.decide(0.03)
        assert output.command == STOP and output.status.reason is Reason.ESTOP_LATCHED, kind
        assert output.status.estop_pressed is True


@pytest.mark.slow
@pytest.mark.parametrize("key", list(Input))
def test_no_malformed_payload_releases_or_moves_slow(policy: Path, key: Input) -> None:
    """10,000 payloads per key, and a 10 MB one."""
    kinds = check_no_malformed_payload_releases_or_moves(
        PolicyRuntime(policy), key, 10_000, seed=1800, max_bytes=10 << 20
    )
    print(key.value, sum(kinds.values()), dict(sorted(kinds.items())))


def test_a_target_point_key_refuses_malformed_points_too(make_policy: PolicyFactory) -> None:
    runtime = PolicyRuntime(make_policy("toycar-inertia"))
    c = Controller(runtime, SafetySettings(target_kind="point"))
    assert c.receive(Input.POSE, pose_payload(), 0.0) is None
    for kind, payload in malformed("point", np.random.default_rng(20), CASES_PER_KEY, 1 << 20):
        assert c.receive(Input.TARGET, payload, 0.01), kind
        assert c.decide(0.01).status.reason is Reason.NO_TARGET, kind
    assert c.receive(Input.TARGET, wire.encode_point_msg(Pose2D(0.0, "map", 5, 5)), 0.02) is None
