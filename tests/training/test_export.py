"""The exported policy file: self-contained, checked by onnx, carrying its contract, and
computing what the torch network computes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
import pytest

from contracts.actions import Action
from contracts.policy_file import INPUT_NAME, OUTPUT_NAME, PolicyContract
from controller.onnx_file import read_onnx
from controller.policy import PolicyRuntime
from sim.evaluate import EvalSettings, StreamPolicyAgent, evaluate
from sim.world import observe, reset, step
from tests.conftest import PolicyFactory, policy_network
from training.agent import TorchAgent
from training.export import torch_q_values


def _random_windows(count: int, frame_size: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    windows = rng.uniform(0.0, 1.0, size=(count, 5, frame_size)).astype(np.float32)
    bearing = rng.uniform(-math.pi, math.pi, size=(count, 5))
    windows[..., -2], windows[..., -1] = np.sin(bearing), np.cos(bearing)
    return windows


def test_the_file_is_self_contained_and_passes_the_onnx_checker(
    make_policy: PolicyFactory,
) -> None:
    path = make_policy("walls-inertia", "recurrent", 512)
    assert sorted(p.name for p in path.parent.glob(path.stem + "*")) == [path.name]
    model = onnx.load(str(path))
    onnx.checker.check_model(model, full_check=True)
    assert [i.name for i in model.graph.input] == [INPUT_NAME]
    assert [o.name for o in model.graph.output] == [OUTPUT_NAME]
    assert all(
        not t.HasField("data_location") or t.data_location == 0 for t in model.graph.initializer
    )


def test_the_metadata_carries_the_contract_of_the_training_world(
    make_policy: PolicyFactory,
) -> None:
    contract = PolicyContract.from_metadata(
        read_onnx(make_policy("walls-inertia")).metadata, "policy"
    )
    assert (contract.window_length, contract.num_beams, contract.max_range_m) == (5, 720, 20.0)
    assert contract.control_period_s == 0.2
    assert contract.dynamics == "inertia" and contract.scenario == "walls-inertia"
    forward, left, right = contract.actions
    assert (forward.linear_mps, forward.angular_radps) == (0.5, 0.0)
    assert (left.linear_mps, left.angular_radps) == (0.0, 0.5)
    assert (right.linear_mps, right.angular_radps) == (0.0, -0.5)


def test_increment_actions_are_their_steps_spread_over_one_control_period(
    make_policy: PolicyFactory,
) -> None:
    contract = PolicyContract.from_metadata(
        read_onnx(make_policy("toycar-increment")).metadata, "policy"
    )
    assert contract.num_beams == 0
    assert contract.actions[Action.FORWARD].linear_mps == pytest.approx(0.2 / 0.2)
    assert contract.actions[Action.RIGHT].angular_radps == pytest.approx(-0.2 / 0.2)


@pytest.mark.parametrize(
    ("scenario", "kind", "hidden"),
    [
        ("walls-inertia", "recurrent", 512),
        ("walls-inertia", "feedforward", 512),
        ("toycar-inertia", "recurrent", 64),
    ],
)
def test_onnxruntime_and_numpy_compute_the_torch_q_values(
    make_policy: PolicyFactory, scenario: str, kind: str, hidden: int
) -> None:
    path = make_policy(scenario, kind, hidden)
    _, network = policy_network(scenario, kind, hidden, 0)
    windows = _random_windows(1000, network.frame_size)
    expected = torch_q_values(network, windows)
    onnx_q = PolicyRuntime(path).q_function(windows)
    numpy_q = PolicyRuntime(path, backend="numpy").q_function(windows)
    assert np.abs(onnx_q - expected).max() <= 1e-4
    assert np.abs(numpy_q - onnx_q).max() <= 1e-5


def test_the_file_picks_the_torch_action_at_every_step_of_recorded_episodes(
    make_policy: PolicyFactory,
) -> None:
    world, network = policy_network("walls-inertia", "recurrent", 64, 0)
    worlds = 8
    torch_agent = TorchAgent(network, worlds, 5, world.lidar.max_range_m if world.lidar else 20)
    runtime = PolicyRuntime(make_policy("walls-inertia", "recurrent", 64), num_streams=worlds)
    state = reset(world, np.full(worlds, 7), np.arange(worlds))
    observation = observe(world, state)
    torch_agent.start(np.arange(worlds), np.arange(worlds))
    steps = 0
    for _ in range(60):
        expected = torch_agent.act(observation)
        actions, _ = runtime.step_batch(observation.scan_m, observation.target_features())
        np.testing.assert_array_equal(actions, expected)
        steps += worlds
        state, observation, transition = step(world, state, expected)
        done = np.flatnonzero(transition.terminated | transition.truncated)
        torch_agent.start(done, done)
        runtime.reset(done)
    assert steps == 480


def test_the_file_scores_what_the_torch_network_scores_with_the_same_seeds(
    make_policy: PolicyFactory,
) -> None:
    world, network = policy_network("walls-increment", "recurrent", 64, 1)
    settings = EvalSettings(episodes=24, max_episode_steps=80, num_worlds=8)
    from_torch = evaluate(world, TorchAgent(network, 8, 5, 20.0), settings)
    runtime = PolicyRuntime(make_policy("walls-increment", "recurrent", 64, 1), num_streams=8)
    from_file = evaluate(world, StreamPolicyAgent(runtime, 8), settings)
    assert from_file == from_torch


def test_the_reader_returns_every_weight_as_onnx_does(make_policy: PolicyFactory) -> None:
    path = make_policy("walls-inertia", "recurrent", 64)
    ours = read_onnx(path).initializers
    theirs = {t.name: onnx.numpy_helper.to_array(t) for t in onnx.load(str(path)).graph.initializer}
    assert ours.keys() == theirs.keys()
    for name, array in theirs.items():
        assert ours[name].dtype == array.dtype and np.array_equal(ours[name], array), name


def test_weights_in_a_separate_file_are_refused_by_the_numpy_reader(
    make_policy: PolicyFactory, tmp_path: Path
) -> None:
    from contracts.errors import PolicyFileError

    model = onnx.load(str(make_policy("walls-inertia", "recurrent", 64)))
    split = tmp_path / "split.onnx"
    onnx.save_model(model, str(split), save_as_external_data=True, size_threshold=0)
    with pytest.raises(PolicyFileError, match="separate file"):
        read_onnx(split)
