"""`qnav lab diagnose`: the measurements that tell memorising from learning."""

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from qnav.lab.diagnose import _turns_towards_target, diagnose
from qnav.sim.config import scenario
from qnav.training.run_folder import load_network
from tests import tiny_training

TINY = replace(tiny_training.TINY, hidden_size=16, eval_every_episodes=0, final_eval_episodes=4)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from qnav.training.run import train

    run_dir = tmp_path_factory.mktemp("diagnose") / "run"
    train(scenario("obstacles-increment"), TINY, run_dir, progress=False)
    return run_dir


def test_a_diagnosis_measures_fractions_and_errors_and_repeats_exactly(tiny_run: Path) -> None:
    first = diagnose(tiny_run, fresh_episodes=4, samples=64)
    assert first == diagnose(tiny_run, fresh_episodes=4, samples=64)
    assert first.replay_td_mse >= 0 and first.fresh_td_mse >= 0
    assert 0 <= first.turns_towards_target <= 1 and 0 <= first.test_success <= 1
    assert sum(first.action_mix) == pytest.approx(1.0)
    assert first.lidar_gate_std > 0 and first.target_gate_std > 0
    assert len(first.dead_channels) == 3 and all(0 <= d <= 8 for d in first.dead_channels)


def test_layouts_saved_and_lost_against_the_blind_controller_add_up_to_the_success_gap(
    tiny_run: Path,
) -> None:
    diagnosis = diagnose(tiny_run, fresh_episodes=4, samples=64)
    against = diagnosis.against_blind
    assert against.layouts == 200  # the test protocol's layouts
    gap = round((diagnosis.test_success - against.blind_success) * against.layouts)
    assert against.saved - against.lost == gap
    assert 0 < against.blind_success < 1  # obstacles-increment: the blind controller loses some


def test_a_network_blind_to_the_target_never_seems_to_turn_towards_it(tiny_run: Path) -> None:
    network, settings = load_network(tiny_run)
    assert network.lstm is not None
    weight = network.lstm.weight_ih_l0
    assert isinstance(weight, torch.Tensor)
    with torch.no_grad():
        weight[:, -3:] = 0.0
    # The same action whichever side the target is on: towards it on one side at most.
    assert _turns_towards_target(network, settings) <= 0.5


def test_qnav_diagnose_prints_the_gap_and_the_action_mix(tiny_run: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "qnav", "lab", "diagnose", str(tiny_run), "--fresh-episodes", "4"],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "TD error (mse): replay" in result.stdout
    assert "greedy test actions: forward" in result.stdout
    assert "against the blind go-to-target controller (" in result.stdout
    assert "dead lidar channels per convolution: " in result.stdout
