"""The malformed-payload generators (tests/contracts/malformed.py) against the decoders: every
payload they make is refused, by the decoder or by the consumer's rule named with it."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from qnav.contracts import wire
from qnav.firmware_bridge import mapping
from qnav.firmware_bridge.core import parse_request
from qnav.firmware_bridge.settings import FailsafeSettings, OutputSettings
from tests.contracts.malformed import CANONICAL_BOOLS, MESSAGES, malformed, well_formed


def twist_refused(payload: bytes) -> bool:
    """As the bridge takes a command: decoded, then its plausibility check with the defaults."""
    try:
        twist = wire.decode_twist_msg(payload)
    except wire.WireError:
        return True
    factor = FailsafeSettings().implausible_factor
    return mapping.implausible(twist, OutputSettings(), factor) is not None


def request_refused(payload: bytes) -> bool:
    """A vehicle request as the bridge reads it (decode_json_msg, then its own parse): refused,
    or asking for nothing (`{"arm": null}` reads as no request: it arms nothing)."""
    try:
        arm, mode = parse_request(wire.decode_json_msg(payload))
    except (wire.WireError, ValueError):
        return True
    return arm is None and mode is None


def bool_refused(payload: bytes) -> bool:
    try:
        wire.decode_bool_msg(payload)
    except wire.WireError:
        return True
    return False


def test_the_valid_payloads_decode() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        wire.decode_scan_msg(well_formed("scan", rng))
        wire.decode_pose_msg(well_formed("pose", rng))
        wire.decode_point_msg(well_formed("point", rng))
        wire.decode_bool_msg(well_formed("bool", rng))
        assert not twist_refused(well_formed("twist", rng))
        assert not request_refused(well_formed("json", rng))
    for payload in CANONICAL_BOOLS:
        assert not bool_refused(payload)


@pytest.mark.parametrize(
    ("message", "refused"),
    [("twist", twist_refused), ("json", request_refused), ("bool", bool_refused)],
)
def test_every_generated_twist_request_and_bool_is_refused(message: str, refused: object) -> None:
    assert callable(refused)
    kinds: Counter[str] = Counter()
    for kind, payload in malformed(message, np.random.default_rng(11), 2000):
        assert refused(payload), (kind, payload[:64].hex())
        kinds[kind] += 1
    assert len(kinds) >= 8, kinds  # every way of breaking a message is exercised


def test_the_generators_are_seeded_and_cover_every_message() -> None:
    for message in MESSAGES:
        first = list(malformed(message, np.random.default_rng(5), 50, max_bytes=0))
        again = list(malformed(message, np.random.default_rng(5), 50, max_bytes=0))
        assert first == again and len(first) == 50
