"""The evaluations during training: a run given no gauge (the product alone, without the lab's)
still evaluates, and leaves the decisive_ columns empty even in an obstacle world."""

import csv
import math
from dataclasses import replace
from pathlib import Path

from qnav.sim.config import scenario
from qnav.training.run import train
from tests import tiny_training

TINY = replace(tiny_training.TINY, episodes=4)


def test_a_run_without_a_gauge_evaluates_and_leaves_the_decisive_columns_empty(
    tmp_path: Path,
) -> None:
    train(scenario("obstacles-increment"), TINY, tmp_path, progress=False)
    with (tmp_path / "progress.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert rows[-1]["eval_success"] and not rows[-1]["decisive_safe"]
    assert not rows[-1]["decisive_balanced"]
    assert not math.isnan(float(rows[-1]["eval_success"]))
