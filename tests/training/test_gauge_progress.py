"""Training reports the decisive-state gauge with each evaluation in obstacle worlds."""

import csv
import math
from dataclasses import replace
from pathlib import Path

from qnav.sim.config import scenario
from qnav.training.config import FAST
from qnav.training.run import train

TINY = replace(
    FAST,
    episodes=8,
    hidden_size=8,
    parallel_worlds=4,
    iterations_per_episode=1,
    batch_size=8,
    eval_every_episodes=4,
    eval_episodes=2,
    final_eval_episodes=2,
    max_episode_steps=30,
    warmup_episodes=2,
    threads=1,
    gauge_episodes=4,
)


def test_each_evaluation_in_an_obstacle_world_reports_the_share_of_safe_choices(
    tmp_path: Path,
) -> None:
    train(scenario("obstacles-increment"), TINY, tmp_path, progress=False)
    with (tmp_path / "progress.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    evaluated = [row for row in rows if row["eval_success"]]
    assert len(evaluated) == 2
    assert all(0.0 <= float(row["decisive_safe"]) <= 1.0 for row in evaluated)
    assert all(0.0 <= float(row["decisive_balanced"]) <= 1.0 for row in evaluated)


def test_walls_only_worlds_have_no_gauge(tmp_path: Path) -> None:
    train(scenario("walls-increment"), replace(TINY, episodes=4), tmp_path, progress=False)
    with (tmp_path / "progress.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert rows[-1]["eval_success"] and not rows[-1]["decisive_safe"]
    assert not math.isnan(float(rows[-1]["eval_success"]))
