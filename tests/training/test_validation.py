"""The evaluations during training: each fills progress.csv's eval_ columns, even in an obstacle
world, and nothing else (the decisive-state gauge's columns were retired: docs/log/retired.md)."""

import csv
import math
from dataclasses import replace
from pathlib import Path

from qnav.sim.config import scenario
from qnav.training.run import train
from qnav.training.run_folder import PROGRESS_COLUMNS
from tests import tiny_training

TINY = replace(tiny_training.TINY, episodes=4)


def test_a_run_evaluates_into_the_eval_columns_and_writes_no_retired_ones(tmp_path: Path) -> None:
    train(scenario("obstacles-increment"), TINY, tmp_path, progress=False)
    with (tmp_path / "progress.csv").open() as handle:
        reader = csv.DictReader(handle)
        rows = list(reader)
    assert tuple(reader.fieldnames or ()) == PROGRESS_COLUMNS
    assert rows[-1]["eval_success"] and not math.isnan(float(rows[-1]["eval_success"]))
    assert "decisive" not in (tmp_path / "results.json").read_text()
