"""Training runs as a user starts them: real processes, a real kill, a real resume."""

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.policy_file import PolicyContract
from qnav.controller.onnx_file import read_onnx
from qnav.sim.config import scenario
from qnav.training.config import FAST
from qnav.training.episode_log import read_rounds
from qnav.training.run import last_validation, train
from qnav.training.run_folder import read_settings

TINY = [
    "--train-set", "train.hidden_size=16",
    "--train-set", "train.parallel_worlds=4",
    "--train-set", "train.iterations_per_episode=1",
    "--train-set", "train.batch_size=8",
    "--train-set", "train.eval_every_episodes=8",
    "--train-set", "train.eval_episodes=4",
    "--train-set", "train.final_eval_episodes=4",
    "--train-set", "train.max_episode_steps=30",
    "--train-set", "train.warmup_episodes=2",
]  # fmt: skip


def _train_command(run_dir: Path, episodes: int) -> list[str]:
    return [
        sys.executable, "-m", "qnav", "train", "--scenario", "walls-increment", "--seed", "3",
        "--episodes", str(episodes), "--run-dir", str(run_dir), "--quiet", *TINY,
    ]  # fmt: skip


def test_a_run_writes_settings_progress_model_and_results(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    result = subprocess.run(
        _train_command(run_dir, 12), capture_output=True, text=True, timeout=300, check=False
    )
    assert result.returncode == 0, result.stderr
    for name in ("settings.toml", "progress.csv", "success.png", "model.pt", "results.json"):
        assert (run_dir / name).exists(), name
    results = json.loads((run_dir / "results.json").read_text())
    assert results["episodes"] == 12
    assert results["test"]["episodes"] == 4
    assert read_settings(run_dir).train.seed == 3
    assert sum(len(r) for r in read_rounds(run_dir / "episodes")) == 12
    policy = subprocess.run(
        [sys.executable, "-m", "qnav", "eval", "--policy", str(run_dir), "--episodes", "3",
         "--json"],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert policy.returncode == 0, policy.stderr
    assert json.loads(policy.stdout)["episodes"] == 3
    # --set changes the run's own world (it was ignored without --scenario)
    changed = subprocess.run(
        [sys.executable, "-m", "qnav", "eval", "--policy", str(run_dir), "--set",
         "max_episode_steps=7", "--print-config"],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert changed.returncode == 0, changed.stderr
    assert "max_episode_steps = 7" in changed.stdout


def test_an_exported_run_scores_what_its_torch_network_scores(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    trained = subprocess.run(
        _train_command(run_dir, 8), capture_output=True, text=True, timeout=300, check=False
    )
    assert trained.returncode == 0, trained.stderr
    policy = tmp_path / "policy.onnx"
    exported = subprocess.run(
        [sys.executable, "-m", "qnav", "export", str(run_dir), "-o", str(policy),
         "--eval-episodes", "6", "--quiet"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert exported.returncode == 0, exported.stderr
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("policy")] == ["policy.onnx"]
    contract = PolicyContract.from_metadata(read_onnx(policy).metadata, "policy")
    assert contract.training_run == str(run_dir)
    assert contract.evaluation["episodes"] == 6

    def evaluate(target: Path, *extra: str) -> dict[str, float]:
        done = subprocess.run(
            [sys.executable, "-m", "qnav", "eval", "--policy", str(target), "--episodes", "6",
             "--max-episode-steps", "60", "--json", *extra],
            capture_output=True, text=True, timeout=300, check=False,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        return dict(json.loads(done.stdout))

    from_torch = evaluate(run_dir)
    assert evaluate(policy) == from_torch
    assert evaluate(policy, "--backend", "numpy") == from_torch


def test_a_killed_run_resumes_without_losing_a_completed_episode(tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    process = subprocess.Popen(
        _train_command(run_dir, 40), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    # Kill it as soon as a first round is on disk (waiting on the file, not on the clock, so a
    # slow or a fast machine kills it mid-run alike).
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and not list((run_dir / "episodes").glob("round-*.npz")):
        time.sleep(0.01)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    collected = sum(len(r) for r in read_rounds(run_dir / "episodes"))
    assert 0 < collected < 40, "the kill should land mid-run"
    resumed = subprocess.run(
        _train_command(run_dir, 40), capture_output=True, text=True, timeout=600, check=False
    )
    assert resumed.returncode == 0, resumed.stderr
    rounds = read_rounds(run_dir / "episodes")
    assert sum(len(r) for r in rounds) == 40
    assert len(list((run_dir / "episodes").glob("round-*.npz"))) == 10  # no round written twice
    assert json.loads((run_dir / "results.json").read_text())["episodes"] == 40


def test_a_run_folder_refuses_other_settings(tmp_path: Path) -> None:
    world = scenario("walls-increment")
    settings = replace(
        FAST, episodes=4, parallel_worlds=4, hidden_size=8, iterations_per_episode=0.0,
        warmup_episodes=0, eval_every_episodes=0, final_eval_episodes=2,
    )  # fmt: skip
    train(world, settings, tmp_path, progress=False)
    with pytest.raises(ConfigError, match="other settings"):
        train(world, replace(settings, seed=9), tmp_path, progress=False)


def test_the_progress_bar_shows_the_last_validation_not_nan_between_them() -> None:
    assert last_validation([]) == "-"
    rows = [{"loss": 1.0}, {"loss": 0.5, "eval_success": 0.75}, {"loss": 0.4}]
    assert last_validation(rows) == "0.75"
