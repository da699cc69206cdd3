"""The BARN table of docs/results.md: one row per baseline file, the seeds of a learner
averaged, training cost shown, BARN's published DWA as context."""

from __future__ import annotations

import json
from pathlib import Path

from qnav.training.barn_results import barn_goals, barn_lines, barn_rows, barn_table


def _save(folder: Path, name: str, success: float, **extra: object) -> None:
    result = {
        "agent": f"agent {name}",
        "success": success,
        "collision": 1.0 - success,
        "timeout": 0.0,
        "metric": success / 2,
        "loops": 0.0,
        **extra,
    }
    (folder / f"{name}.json").write_text(json.dumps(result))


def test_a_learners_seeds_make_one_row_with_their_mean_and_training_cost(tmp_path: Path) -> None:
    _save(tmp_path, "dwa", 0.5)
    for seed, success in enumerate((0.8, 0.9)):
        training = {"episodes": 640, "minutes": 40.0 + seed}
        _save(tmp_path, f"dagger-recurrent-seed{seed}", success, training=training)
    lines = barn_table(barn_rows(tmp_path))
    rows = {line.split(" | ")[0].strip("| "): line for line in lines[2:]}
    assert "| 2 | 0.850 +- 0.050 |" in rows["dagger-recurrent"]
    assert "640 / 41" in rows["dagger-recurrent"]
    assert "| 1 | 0.500 |" in rows["dwa"]
    assert "0.880" in lines[-1] and "BARN's move_base + DWA" in lines[-1]


def test_no_saved_result_means_no_barn_section(tmp_path: Path) -> None:
    assert barn_lines(tmp_path) == []
    (tmp_path / "barn").mkdir()
    _save(tmp_path / "barn", "goto", 0.06)
    assert barn_lines(tmp_path)[1].startswith("## BARN")


def test_each_goal_says_met_or_not_met_with_its_numbers(tmp_path: Path) -> None:
    _save(tmp_path, "dwa", 0.8)
    _save(tmp_path, "goto", 0.1)
    for seed, success in enumerate((0.7, 0.74)):
        _save(tmp_path, f"dagger-recurrent-committed-seed{seed}", success)
    goals = barn_goals(barn_rows(tmp_path))
    assert goals[0] == "- the recurrent policy >= 0.90: 0.720, **not met** (goal 0.900)"
    assert "against dwa 0.800, **not met** (goal 0.850)" in goals[1]
    assert "against goto 0.100, met (goal 0.500)" in goals[2]
    assert len(goals) == 3  # no feedforward row saved: its goal is left out
