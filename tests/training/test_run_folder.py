"""A run folder's settings: what it was started with, and folders older than a removal."""

import csv
from dataclasses import replace
from pathlib import Path

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import to_toml
from qnav.sim.config import scenario
from qnav.training.config import TrainSettings
from qnav.training.run_folder import (
    LAST_COMMIT_WITH_EXPERIMENTS,
    PROGRESS_COLUMNS,
    RunFolder,
    RunSettings,
    read_settings,
)

SETTINGS = RunSettings(scenario("walls-increment"), TrainSettings(hidden_size=8, seed=4))


def _started_with(tmp_path: Path, extra: str) -> Path:
    """A run folder whose settings.toml also holds `extra` lines in its [train] table."""
    RunFolder(tmp_path).start(SETTINGS)
    path = tmp_path / "settings.toml"
    path.write_text(to_toml(SETTINGS).replace("[train]\n", "[train]\n" + extra))
    return tmp_path


def test_a_started_folder_reads_back_its_settings_and_refuses_others(tmp_path: Path) -> None:
    RunFolder(tmp_path).start(SETTINGS)
    assert read_settings(tmp_path) == SETTINGS
    other = RunSettings(SETTINGS.world, TrainSettings(hidden_size=8, seed=5))
    with pytest.raises(ConfigError, match="other settings"):
        RunFolder(tmp_path).start(other)


def test_a_folder_from_before_the_removal_reads_while_the_removed_experiments_were_off(
    tmp_path: Path,
) -> None:
    older = (
        "mirror_probability = 0.0\nnext_scan_weight = 0.0\nnext_scan_sectors = 36\n"
        'demonstration_episodes = 0\ndemonstration_margin = 0.2\nencoder_init = "default"\n'
        "obstacle_risk_head = false\nevery_action_weight = 0.0\n"
        'epsilon_min = 0.0\nhold_steps = 5\nloss = "mse"\npriority_exponent = 0.0\n'
        "priority_correction_start = 0.7\nobstacle_inputs = false\n"
    )
    assert read_settings(_started_with(tmp_path, older)) == SETTINGS


@pytest.mark.parametrize(
    ("line", "name"),
    [
        ("next_scan_weight = 1.0\n", "train.next_scan_weight"),
        ('encoder_init = "centred"\n', "train.encoder_init"),
        ("demonstration_episodes = 40\ndemonstration_margin = 0.1\n", "demonstration_episodes"),
    ],
)
def test_a_folder_that_used_a_removed_experiment_is_refused_by_name(
    tmp_path: Path, line: str, name: str
) -> None:
    with pytest.raises(ConfigError, match=name) as refused:
        read_settings(_started_with(tmp_path, line))
    assert LAST_COMMIT_WITH_EXPERIMENTS in str(refused.value)


@pytest.mark.parametrize(
    ("line", "commit"),
    [
        ("obstacle_risk_head = true\n", "cbd23ae"),
        ("every_action_weight = 1.0\n", "cbd23ae"),
        ("doom_bound_weight = 1.0\n", "97b3cd2"),
        ("epsilon_min = 0.1\n", "d3e9697"),
        ("hold_steps = 1\n", "d3e9697"),
        ('loss = "huber"\n', "d3e9697"),
        ("priority_exponent = 0.6\npriority_correction_start = 0.4\n", "d3e9697"),
        ("obstacle_inputs = true\n", "d3e9697"),
    ],
)
def test_a_folder_of_a_later_removed_experiment_names_the_last_commit_that_has_it(
    tmp_path: Path, line: str, commit: str
) -> None:
    with pytest.raises(ConfigError, match=line.split(maxsplit=1)[0]) as refused:
        read_settings(_started_with(tmp_path, line))
    assert commit in str(refused.value)


def test_a_refused_resume_names_the_settings_that_differ_and_threads_may_differ(
    tmp_path: Path,
) -> None:
    RunFolder(tmp_path).start(SETTINGS)
    other = RunSettings(SETTINGS.world, replace(SETTINGS.train, seed=5, hidden_size=4))
    with pytest.raises(ConfigError, match=r"train\.hidden_size, train\.seed\)"):
        RunFolder(tmp_path).start(other)
    RunFolder(tmp_path).start(RunSettings(SETTINGS.world, replace(SETTINGS.train, threads=7)))
    assert read_settings(tmp_path).train.threads == 7


@pytest.mark.parametrize("episodes", [400, 0])
def test_a_folder_from_before_the_gauge_was_retired_reads_and_resumes_whatever_its_episodes(
    tmp_path: Path, episodes: int
) -> None:
    folder = _started_with(tmp_path, f"gauge_episodes = {episodes}\n")
    assert read_settings(folder) == SETTINGS
    RunFolder(folder).start(SETTINGS)  # resumes: the retired measurement is no difference


def test_a_resumed_history_keeps_the_retired_gauge_columns_after_the_others(
    tmp_path: Path,
) -> None:
    old = {"episodes": 8, "eval_success": 0.5, "decisive_safe": 0.6, "decisive_balanced": 0.5}
    history = [old, {"episodes": 16, "loss": 0.1}]
    RunFolder(tmp_path).write_progress(history, "resumed")
    with (tmp_path / "progress.csv").open() as handle:
        reader = csv.DictReader(handle)
        rows = list(reader)
    assert reader.fieldnames == [*PROGRESS_COLUMNS, "decisive_safe", "decisive_balanced"]
    assert rows[0]["decisive_safe"] == "0.6" and rows[1]["decisive_safe"] == ""
    RunFolder(tmp_path).write_progress(history[1:], "new")
    assert (tmp_path / "progress.csv").read_text().splitlines()[0] == ",".join(PROGRESS_COLUMNS)
