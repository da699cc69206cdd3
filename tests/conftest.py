"""Shared fixtures: exported policy files (real ONNX, made once per test session)."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from qnav.sim.config import WorldConfig
    from qnav.training.networks import QNetwork

PolicyFactory = Callable[..., Path]


@pytest.fixture(scope="session", autouse=True)
def _private_cache(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Collected gauge states go to a folder of this session, not the user's cache."""
    os.environ["QNAV_CACHE"] = str(tmp_path_factory.mktemp("cache"))


@pytest.fixture
def processes() -> Iterator[list[subprocess.Popen[Any]]]:
    """Child processes a test starts (it appends them): the ones still running when it ends, a
    failed test's say, are killed."""
    started: list[subprocess.Popen[Any]] = []
    yield started
    for process in started:
        if process.poll() is None:
            process.kill()
            process.wait()


@pytest.fixture(scope="session")
def make_policy(tmp_path_factory: pytest.TempPathFactory) -> PolicyFactory:
    """`make_policy(scenario, kind, hidden_size, seed)` -> an untrained exported policy file.

    Files are cached for the session: exporting takes seconds. Weights come from
    `torch.manual_seed(seed)`, so a test can rebuild the same torch network with
    `policy_network(...)`.
    """
    cache: dict[tuple[str, str, int, int], Path] = {}
    root = tmp_path_factory.mktemp("policies")

    def make(
        scenario: str = "walls-inertia",
        kind: str = "recurrent",
        hidden_size: int = 64,
        seed: int = 0,
    ) -> Path:
        spec = (scenario, kind, hidden_size, seed)
        if spec not in cache:
            from qnav.training.export import export_onnx, policy_contract

            world, network = policy_network(*spec)
            path = root / f"{scenario}-{kind}-h{hidden_size}-s{seed}.onnx"
            export_onnx(network, policy_contract(network, world, 5, "tests", "test"), path)
            cache[spec] = path
        return cache[spec]

    return make


def with_metadata(source: Path, target: Path, entries: dict[str, object]) -> Path:
    """A copy of the policy file `source` at `target` with some `qnav.*` entries set (JSON),
    added where the file has none."""
    import json

    import onnx

    model = onnx.load(str(source))
    missing = dict(entries)
    for entry in model.metadata_props:
        if entry.key in entries:
            entry.value = json.dumps(missing.pop(entry.key))
    for key, value in missing.items():
        model.metadata_props.add(key=key, value=json.dumps(value))
    onnx.save(model, str(target))
    return target


def policy_network(
    scenario: str, kind: str, hidden_size: int, seed: int
) -> tuple[WorldConfig, QNetwork]:
    """The world and the (untrained, seeded) torch network behind `make_policy`'s file."""
    import torch

    from qnav.sim.config import scenario as load_scenario
    from qnav.training.networks import QNetwork

    world = load_scenario(scenario)
    torch.manual_seed(seed)
    beams = world.lidar.num_beams if world.lidar else None
    return world, QNetwork(kind, beams, hidden_size).eval()  # type: ignore[arg-type]
