"""Fixtures of the controller's tests."""

from __future__ import annotations

import pytest

from qnav.contracts.daemon import free_port


@pytest.fixture
def endpoint() -> str:
    """A loopback zenoh endpoint on a port free a moment ago (the car's session listens there)."""
    return f"tcp/127.0.0.1:{free_port()}"
