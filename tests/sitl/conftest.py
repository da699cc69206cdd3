"""Fixtures of the ArduPilot-in-the-loop tests: skipped, with the reason, without a SITL binary."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

from qnav.sitl import SITL_ENV, SITL_PARAMS
from tests.sitl.harness import (
    BridgeProcess,
    Observer,
    Sitl,
    Zenoh,
    sitl_binary,
)

SKIP_REASON = (
    f"{SITL_ENV} is not set: build ArduPilot Rover SITL (docs/bridge-testing.md, 'Getting a SITL "
    f"binary') and run `{SITL_ENV}=/path/to/ardurover make test-sitl`"
)


@pytest.fixture(autouse=True)
def _needs_sitl() -> None:
    binary = sitl_binary()
    if binary is None:
        pytest.skip(SKIP_REASON)
    if not binary.is_file():
        pytest.fail(f"{SITL_ENV}={binary} is not a file")


@pytest.fixture
def stack() -> Iterator[ExitStack]:
    with ExitStack() as stack:
        yield stack


@pytest.fixture
def zenoh(stack: ExitStack) -> Zenoh:
    peer = Zenoh()
    stack.callback(peer.close)
    return peer


@pytest.fixture
def start_sitl(stack: ExitStack, tmp_path: Path) -> Callable[..., tuple[Sitl, Observer]]:
    """`start_sitl(extra_params=[...])`: a booting ardurover and the test's observer on it."""

    def start(extra_params: list[Path] | None = None) -> tuple[Sitl, Observer]:
        binary = sitl_binary()
        assert binary is not None
        sitl = Sitl(binary, tmp_path / "sitl", [SITL_PARAMS, *(extra_params or [])])
        stack.callback(sitl.stop)
        sitl.start()
        observer = Observer(sitl.serial0)
        stack.callback(observer.close)
        return sitl, observer

    return start


@pytest.fixture
def start_bridge(stack: ExitStack, tmp_path: Path, zenoh: Zenoh) -> Callable[..., BridgeProcess]:
    """`start_bridge(connection, "output.mode=\\"guided\\"", ...)`: `qnav bridge` as a process."""
    count = [0]

    def start(connection: str, *assignments: str, config: Path | None = None) -> BridgeProcess:
        count[0] += 1
        bridge = BridgeProcess(
            config or Path(__file__).resolve().parents[2] / "config" / "bridge-sitl.toml",
            tmp_path / f"bridge{count[0]}.log",
            [
                f'zenoh.connect=["tcp/127.0.0.1:{zenoh.port}"]',
                f'mavlink.connection="{connection}"',
                *assignments,
            ],
        )
        stack.callback(bridge.close)
        return bridge

    return start
