"""A training run's folder: its settings, checkpoints, episodes, progress and results.

    settings.toml      world and learner settings (a resumed run must match them)
    episodes/          collected episodes, one file per round (no completed episode is lost)
    checkpoint.pt      networks, optimiser, counters, history (written atomically each round)
    progress.csv       one row per round: episodes, iterations, time, exploration, success
    success.png        success during training (the paper's figures 5, 6, 8, 9)
    snapshots/         the online network every `snapshot_every_episodes` (if asked)
    best.pt            the network of the best validation so far (with `keep_best`)
    model.pt           the final online network with its world and learner settings
    results.json       the final test under the paper's protocol

Every file is written to a temporary name and renamed, so a run killed at any moment leaves
whole files only. This module reads and writes them; `training.run` is the loop that fills it.
"""

from __future__ import annotations

import csv
import json
import subprocess
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import from_dict, to_dict, to_toml
from qnav.sim.config import WorldConfig
from qnav.training.config import TrainSettings
from qnav.training.episode_log import Episode, read_rounds, write_round
from qnav.training.networks import QNetwork, make_network

LAST_COMMIT_WITH_EXPERIMENTS = "b8dfe92"
"""The last commit with the learner experiments that changed nothing (`REMOVED_SETTINGS`)."""
REMOVED_SETTINGS: dict[str, object] = {
    "mirror_probability": 0.0,
    "obstacle_near_probability": 0.0,
    "obstacle_bootstrap_within_m": 0.0,
    "next_scan_weight": 0.0,
    "next_scan_range_m": 5.0,
    "next_scan_sectors": 72,
    "demonstration_episodes": 0,
    "demonstration_margin": 0.05,
    "demonstration_loss_weight": 1.0,
    "encoder_init": "default",
    "obstacle_risk_head": False,
    "every_action_weight": 0.0,
    "doom_bound_weight": 0.0,
    "epsilon_min": 0.0,
    "hold_steps": 5,
    "loss": "mse",
    "priority_exponent": 0.0,
    "priority_correction_start": 0.4,
    "obstacle_inputs": False,
}
"""Learner settings removed after `LAST_COMMIT_WITH_EXPERIMENTS` (or the commit `_REMOVED_AFTER`
names; docs/learner.md has what they measured), with the values that left them off: a run folder
started before then reads as long as they are off."""
_REMOVED_AFTER = {
    "obstacle_risk_head": "cbd23ae",
    "every_action_weight": "cbd23ae",
    "doom_bound_weight": "97b3cd2",
    **dict.fromkeys(
        ["epsilon_min", "hold_steps", "loss", "priority_exponent", "obstacle_inputs"],
        "d3e9697",
    ),
}
"""The last commit with each setting removed later than `LAST_COMMIT_WITH_EXPERIMENTS`."""
RETIRED_MEASUREMENTS = ("gauge_episodes",)
"""Learner settings of measurements retired after commit 7d4f731 (the decisive-state gauge,
docs/log/retired.md): they changed what a run reported, never what it learned, so a run folder
that holds them reads whatever their value."""
_SWITCHED_BY = {
    "next_scan_range_m": "next_scan_weight",
    "next_scan_sectors": "next_scan_weight",
    "demonstration_margin": "demonstration_episodes",
    "demonstration_loss_weight": "demonstration_episodes",
    "priority_correction_start": "priority_exponent",
}
"""Removed settings that did nothing while another removed setting was off."""
PROGRESS_COLUMNS = (
    "episodes",
    "iterations",
    "wall_s",
    "epsilon",
    "train_success",
    "train_collision",
    "loss",
    "eval_success",
    "eval_collision",
    "eval_unfinished",
    "phase",
)
"""progress.csv's columns; a round without an evaluation leaves the eval_ ones empty. In the
rounds of imitation (phase "imitation"; empty: reinforcement learning), episodes and iterations
count the imitation's and epsilon is the planner's share of the steps."""
RETIRED_PROGRESS_COLUMNS = ("decisive_safe", "decisive_balanced")
"""Columns of the decisive-state gauge, retired after commit 7d4f731: a run resumed
from before then keeps them, after the others, for its rounds that have them."""


def progress_columns(history: list[dict[str, Any]]) -> list[str]:
    """progress.csv's columns for this history: `PROGRESS_COLUMNS`, and the retired ones its
    rounds hold."""
    retired = [c for c in RETIRED_PROGRESS_COLUMNS if any(c in row for row in history)]
    return [*PROGRESS_COLUMNS, *retired]


@dataclass(frozen=True)
class RunSettings:
    """What a run folder's settings.toml holds."""

    SECTION = ""

    world: WorldConfig
    """The world trained in."""
    train: TrainSettings
    """The learner."""


@dataclass
class Progress:
    """Counters and history of a run, saved with every checkpoint."""

    rounds: int = 0
    episodes: int = 0
    iterations: int = 0
    collect_s: float = 0.0
    train_s: float = 0.0
    eval_s: float = 0.0
    best_success: float = -1.0
    imitation_rounds: int = 0
    imitation_iterations: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)


def read_settings(run_dir: Path) -> RunSettings:
    """The world and learner settings a run folder was started with."""
    path = run_dir / "settings.toml"
    if not path.exists():
        raise ConfigError(f"{run_dir} is not a training run: it has no settings.toml")
    values = tomllib.loads(path.read_text())
    values["train"] = without_removed_settings(values.get("train", {}), str(path))
    return from_dict(RunSettings, values)


def without_removed_settings(train: dict[str, Any], where: str) -> dict[str, Any]:
    """Learner settings read from a file less the `REMOVED_SETTINGS` it holds, which must be
    off (a run that used a removed experiment is refused, by the setting's name), and less the
    `RETIRED_MEASUREMENTS`, whatever their value."""
    kept = {}
    for key, value in train.items():
        if key in RETIRED_MEASUREMENTS:
            continue
        if key not in REMOVED_SETTINGS:
            kept[key] = value
            continue
        switch = _SWITCHED_BY.get(key, key)
        if train.get(switch, REMOVED_SETTINGS[switch]) != REMOVED_SETTINGS[switch]:
            raise ConfigError(
                f"{where}: train.{switch} = {train[switch]!r} is an experiment removed after "
                f"commit {_REMOVED_AFTER.get(switch, LAST_COMMIT_WITH_EXPERIMENTS)} "
                "(docs/learner.md); check that commit "
                "out to resume or evaluate this run"
            )
    return kept


RESUMABLE_WITH_OTHER_VALUES = ("train.threads",)
"""Settings a run resumes with other values of: how this machine runs it, not what it learns."""


def differing_settings(saved: RunSettings, wanted: RunSettings) -> list[str]:
    """Dotted names (`train.seed`, `world.obstacles.count`) of the settings whose values
    differ between two runs' settings."""
    before, after = _flat(to_dict(saved)), _flat(to_dict(wanted))
    return sorted(name for name, value in after.items() if before.get(name, _MISSING) != value)


_MISSING = object()


def _flat(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested dict of settings as {dotted name: value}."""
    flat: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, dict):
            flat |= _flat(value, f"{prefix}{key}.")
        else:
            flat[f"{prefix}{key}"] = value
    return flat


class RunFolder:
    """Reads and writes the files of one run folder."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.episodes = path / "episodes"

    def start(self, settings: RunSettings) -> None:
        """Create the folder, or check that the run it holds has these settings."""
        self.path.mkdir(parents=True, exist_ok=True)
        settings_path = self.path / "settings.toml"
        if settings_path.exists():
            differ = differing_settings(read_settings(self.path), settings)
            if [name for name in differ if name not in RESUMABLE_WITH_OTHER_VALUES]:
                raise ConfigError(
                    f"{self.path} holds a run with other settings ({settings_path}: "
                    f"{', '.join(differ)}); resume it with the same settings or choose "
                    "another folder"
                )
        settings_path.write_text(to_toml(settings))

    def checkpoint(self, device: torch.device) -> dict[str, Any] | None:
        """The last checkpoint (`save_checkpoint`), or None if the run has none yet."""
        path = self.path / "checkpoint.pt"
        if not path.exists():
            return None
        return dict(torch.load(path, weights_only=False, map_location=device))

    def save_checkpoint(self, learner: dict[str, Any], progress: Progress) -> None:
        """The learner's state (networks, optimiser) and the run's counters and history."""
        _save({**learner, "progress": asdict(progress)}, self.path / "checkpoint.pt")

    def rounds(self) -> list[list[Episode]]:
        """Every round of episodes collected so far, in order."""
        return read_rounds(self.episodes)

    def write_round(self, round_index: int, episodes: list[Episode]) -> None:
        """Store one collected round."""
        write_round(self.episodes, round_index, episodes)

    def write_progress(self, history: list[dict[str, float]], title: str) -> None:
        """progress.csv, and success.png when the last round has a new evaluation."""
        partial = self.path / "progress.csv.partial"
        with partial.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, progress_columns(history))
            writer.writeheader()
            writer.writerows(history)
        partial.replace(self.path / "progress.csv")
        if "eval_success" in history[-1]:  # the picture changes only with a new evaluation
            from qnav.training.plots import plot_training

            plot_training(history, self.path / "success.png", title)

    def save_snapshot(self, online: QNetwork, progress: Progress) -> None:
        """The online network now, for the action-map figure."""
        snapshots = self.path / "snapshots"
        snapshots.mkdir(exist_ok=True)
        torch.save(
            {"online": online.state_dict(), "iterations": progress.iterations},
            snapshots / f"episodes-{progress.episodes:05d}.pt",
        )

    def save_best(self, online: QNetwork, episodes: int) -> None:
        """The network of the best validation so far."""
        _save({"online": online.state_dict(), "episodes": episodes}, self.path / "best.pt")

    def best(self, device: torch.device) -> dict[str, Any] | None:
        """The best validation's network weights (`save_best`), or None if none was saved."""
        path = self.path / "best.pt"
        if not path.exists():
            return None
        return dict(torch.load(path, weights_only=False, map_location=device)["online"])

    def save_model(self, weights: dict[str, Any], settings: RunSettings) -> None:
        """model.pt: the shipped network with the settings it was trained with."""
        torch.save(
            {"online": weights, "world": to_dict(settings.world), "train": to_dict(settings.train)},
            self.path / "model.pt",
        )

    def results(self) -> dict[str, Any] | None:
        """The final test's results, or None if the run has not finished."""
        path = self.path / "results.json"
        return dict(json.loads(path.read_text())) if path.exists() else None

    def write_results(self, results: dict[str, Any]) -> None:
        """results.json."""
        (self.path / "results.json").write_text(json.dumps(results, indent=2) + "\n")


def _save(saved: dict[str, Any], path: Path) -> None:
    partial = path.parent / (path.name + ".partial")
    torch.save(saved, partial)
    partial.replace(path)


def source_commit() -> str:
    """The git revision of this source tree ("+dirty" if it has uncommitted changes)."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def load_network(run_dir: Path, weights: Path | None = None) -> tuple[QNetwork, RunSettings]:
    """The run's network from `weights` (a file of the run's); by default its final network
    (model.pt), or its latest checkpoint if it has not finished."""
    settings = read_settings(run_dir)
    network = make_network(settings.world, settings.train)
    candidates = [weights] if weights else [run_dir / "model.pt", run_dir / "checkpoint.pt"]
    for path in candidates:
        if path.exists():
            saved = torch.load(path, weights_only=False, map_location="cpu")
            network.load_state_dict(saved["online"])
            network.eval()
            return network, settings
    if weights:
        raise ConfigError(f"{weights} does not exist: nothing to load")
    raise ConfigError(f"{run_dir} has neither model.pt nor checkpoint.pt: nothing to load")
