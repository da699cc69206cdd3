"""The decisive-state gauge `qnav train` hands a run: each evaluation in an obstacle world reports
it; walls-only worlds and `train.gauge_episodes = 0` have none."""

import csv
from dataclasses import replace
from pathlib import Path

from qnav.lab.gauge import training_gauge
from qnav.sim.config import scenario
from qnav.training.run import train
from tests.tiny_training import TINY


def test_each_evaluation_in_an_obstacle_world_reports_the_share_of_safe_choices(
    tmp_path: Path,
) -> None:
    world = scenario("obstacles-increment")
    gauge = training_gauge(world, TINY, progress=False)
    train(world, TINY, tmp_path, progress=False, gauge=gauge)
    with (tmp_path / "progress.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    evaluated = [row for row in rows if row["eval_success"]]
    assert len(evaluated) == 2
    assert all(0.0 <= float(row["decisive_safe"]) <= 1.0 for row in evaluated)
    assert all(0.0 <= float(row["decisive_balanced"]) <= 1.0 for row in evaluated)


def test_walls_only_worlds_and_a_gauge_of_no_episodes_have_no_gauge() -> None:
    assert training_gauge(scenario("walls-increment"), TINY, progress=False) is None
    none = replace(TINY, gauge_episodes=0)
    assert training_gauge(scenario("obstacles-increment"), none, progress=False) is None
    assert training_gauge(scenario("obstacles-increment"), TINY, progress=False) is not None
