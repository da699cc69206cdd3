"""A tiny training run shared by the lab's tests of labels drawn from a run's stored steps."""

from dataclasses import replace
from pathlib import Path

import pytest

from qnav.sim.config import scenario
from tests import tiny_training

TINY_RUN_WORLD = scenario("obstacles-inertia")
"""The world the tiny run is trained in."""


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder of a few tiny training episodes in `TINY_RUN_WORLD`."""
    from qnav.training.run import train

    run_dir = tmp_path_factory.mktemp("redrawn") / "run"
    settings = replace(tiny_training.TINY, eval_every_episodes=0, final_eval_episodes=2)
    train(TINY_RUN_WORLD, settings, run_dir, progress=False)
    return run_dir
