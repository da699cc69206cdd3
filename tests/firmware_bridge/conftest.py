"""Fixtures of the bridge's tests: rigs of real zenoh sessions and real MAVLink over UDP."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from tests.firmware_bridge.rig import Rig, rigs


@pytest.fixture
def make_rig() -> Iterator[Callable[..., Rig]]:
    """`make_rig(bridge={...}, vehicle={...})`: a started rig, closed after the test."""
    yield from rigs()
