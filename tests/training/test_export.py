"""The exported policy file: self-contained, checked by onnx, carrying its contract, and
computing what the torch network computes (its streaming graph, fed a window's frames one by
one, gives the window network's Q values)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import onnx
import pytest

from qnav.contracts.actions import Action
from qnav.contracts.errors import PolicyFileError
from qnav.contracts.policy_file import (
    FRAME_INPUT,
    OUTPUT_NAME,
    STATE_INPUTS,
    STATE_OUTPUTS,
    WINDOW_FORMAT,
    PolicyContract,
)
from qnav.controller.onnx_file import read_onnx
from qnav.controller.policy import BACKENDS, PolicyRuntime, State
from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent, evaluate
from qnav.sim.world import observe, reset, step
from qnav.training.agent import TorchAgent
from qnav.training.export import (
    REEXPORT_KEY,
    export_onnx,
    policy_contract,
    reexport_file,
    torch_q_values,
)
from tests.conftest import PolicyFactory, policy_network
from tests.near_ties import assert_actions_match_but_near_ties


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
    assert all(
        not t.HasField("data_location") or t.data_location == 0 for t in model.graph.initializer
    )


@pytest.mark.parametrize(
    ("kind", "inputs", "outputs"),
    [
        ("recurrent", [FRAME_INPUT, *STATE_INPUTS], [OUTPUT_NAME, *STATE_OUTPUTS]),
        ("feedforward", [FRAME_INPUT], [OUTPUT_NAME]),
    ],
)
def test_the_graph_takes_the_newest_frame_and_the_state_and_keeps_the_parameter_names(
    make_policy: PolicyFactory, kind: str, inputs: list[str], outputs: list[str]
) -> None:
    path = make_policy("walls-inertia", kind, 64)
    model = onnx.load(str(path))
    assert [i.name for i in model.graph.input] == inputs
    assert [o.name for o in model.graph.output] == outputs
    dims = [
        [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim]
        for i in model.graph.input
    ]
    assert dims[0] == ["batch", 723]
    assert all(d == ["batch", 4, 64] for d in dims[1:])
    _, network = policy_network("walls-inertia", kind, 64, 0)
    assert {t.name for t in model.graph.initializer} == set(network.state_dict())


def test_the_metadata_carries_the_contract_of_the_training_world(
    make_policy: PolicyFactory,
) -> None:
    contract = PolicyContract.from_metadata(
        read_onnx(make_policy("walls-inertia")).metadata, "policy"
    )
    assert (contract.window_length, contract.num_beams, contract.max_range_m) == (5, 720, 20.0)
    assert contract.control_period_s == 0.2
    assert contract.dynamics == "inertia" and contract.scenario == "walls-inertia"
    assert (contract.state_slots, contract.state_size) == (4, 64)
    assert contract.format == "qnav-policy/2"
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
    """Each window's frames fed one by one from a fresh state give the torch network's Q."""
    path = make_policy(scenario, kind, hidden)
    _, network = policy_network(scenario, kind, hidden, 0)
    windows = _random_windows(1000, network.frame_size)
    expected = torch_q_values(network, windows)
    onnx_q = PolicyRuntime(path).window_q_values(windows)
    numpy_q = PolicyRuntime(path, backend="numpy").window_q_values(windows)
    assert np.abs(onnx_q - expected).max() <= 1e-4
    assert np.abs(numpy_q - onnx_q).max() <= 1e-5


@pytest.mark.parametrize("backend", ["onnxruntime", "numpy"])
def test_k_frames_flush_whatever_state_the_stream_was_in(
    make_policy: PolicyFactory, backend: str
) -> None:
    path = make_policy("walls-inertia", "recurrent", 64)
    _, network = policy_network("walls-inertia", "recurrent", 64, 0)
    runtime = PolicyRuntime(path, backend=backend)  # type: ignore[arg-type]
    windows = _random_windows(200, network.frame_size, seed=1)
    rng = np.random.default_rng(2)
    state: State | None = State(
        *(rng.uniform(-1, 1, size=(200, 4, 64)).astype(np.float32) for _ in range(2))
    )
    for t in range(5):
        q, state = runtime.step_function(windows[:, t].copy(), state)
    assert np.abs(q - torch_q_values(network, windows)).max() <= 1e-4


@pytest.mark.parametrize("window", [1, 3])
def test_other_window_lengths_carry_k_minus_1_windows_and_compute_the_torch_q_values(
    tmp_path: Path, window: int
) -> None:
    world, network = policy_network("toycar-inertia", "recurrent", 32, 0)
    path = tmp_path / "policy.onnx"
    export_onnx(network, policy_contract(network, world, window, "tests", "test"), path)
    windows = _random_windows(100, network.frame_size)[:, :window].copy()
    expected = torch_q_values(network, windows)
    for backend in BACKENDS:
        runtime = PolicyRuntime(path, backend=backend)
        assert runtime.contract.state_slots == window - 1
        assert np.abs(runtime.window_q_values(windows) - expected).max() <= 1e-4


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
    steps = near_ties = 0
    for t in range(60):
        expected = torch_agent.act(observation)
        _, q = runtime.step_batch(observation.scan_m, observation.target_features())
        # torch's action is the file's best, or within a near-tie of it (tests/near_ties.py).
        near_ties += assert_actions_match_but_near_ties(expected, q, f"step {t}")
        steps += worlds
        state, observation, transition = step(world, state, expected)
        done = np.flatnonzero(transition.terminated | transition.truncated)
        torch_agent.start(done, done)
        runtime.reset(done)
    assert steps == 480
    assert near_ties <= steps // 100  # rare: exact equality but for rounding


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

    model = onnx.load(str(make_policy("walls-inertia", "recurrent", 64)))
    split = tmp_path / "split.onnx"
    onnx.save_model(model, str(split), save_as_external_data=True, size_threshold=0)
    with pytest.raises(PolicyFileError, match="separate file"):
        read_onnx(split)


OLD_EVALUATION = {"success": 0.5, "collision": 0.25, "unfinished": 0.25, "episodes": 4.0}


def _as_window_format(path: Path, folder: Path) -> Path:
    """The file with the metadata of the earlier layout (qnav-policy/1, no state entries)."""
    model = onnx.load(str(path))
    kept = [p for p in model.metadata_props if p.key not in ("qnav.state_slots", "qnav.state_size")]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    for entry in model.metadata_props:
        if entry.key == "qnav.format":
            entry.value = json.dumps(WINDOW_FORMAT)
        elif entry.key == "qnav.evaluation":
            entry.value = json.dumps(OLD_EVALUATION)
    old = folder / "old.onnx"
    onnx.save(model, str(old))
    return old


def test_a_reexported_file_keeps_its_weights_and_metadata_and_computes_the_same(
    make_policy: PolicyFactory, tmp_path: Path
) -> None:
    old = _as_window_format(make_policy("walls-inertia", "recurrent", 64), tmp_path)
    new = tmp_path / "new.onnx"
    reexport_file(old, new)
    before, after = read_onnx(old), read_onnx(new)
    assert before.initializers.keys() == after.initializers.keys()
    for name, array in before.initializers.items():
        assert np.array_equal(after.initializers[name], array), name
    changed = {k for k in before.metadata if before.metadata[k] != after.metadata.get(k)}
    assert changed == {"qnav.format"}
    note = json.loads(after.metadata[REEXPORT_KEY])
    assert note["file"] == str(old) and note["format"] == WINDOW_FORMAT
    contract = PolicyRuntime(new).contract
    assert contract.evaluation == OLD_EVALUATION
    _, network = policy_network("walls-inertia", "recurrent", 64, 0)
    windows = _random_windows(100, network.frame_size)
    q = PolicyRuntime(new).window_q_values(windows)
    assert np.abs(q - torch_q_values(network, windows)).max() <= 1e-4


def test_qnav_export_of_a_policy_file_reexports_it_in_place(
    make_policy: PolicyFactory, tmp_path: Path
) -> None:
    from qnav.cli import main as qnav

    old = _as_window_format(make_policy("walls-inertia", "recurrent", 64), tmp_path)
    assert qnav(["export", str(old), "--quiet"]) != 0  # -o is required for a file
    assert qnav(["export", str(old), "-o", str(old), "--quiet"]) == 0
    contract = PolicyRuntime(old).contract
    assert contract.format == "qnav-policy/2" and contract.training_run == "tests"


def test_an_int8_file_reexported_with_another_turn_commitment_carries_it_and_drops_its_results(
    tmp_path: Path,
) -> None:
    from qnav.cli import main as qnav

    source = Path(__file__).parents[2] / "results" / "barn" / "barn-recurrent.onnx"
    before = PolicyRuntime(source).contract
    assert before.weight_type == "int8" and before.evaluation and before.turn_commitment
    new = tmp_path / "uncommitted.onnx"
    args = ["export", str(source), "-o", str(new), "--no-turn-commitment", "--eval-episodes", "0"]
    assert qnav([*args, "--quiet"]) == 0
    after = PolicyRuntime(new).contract
    assert not after.turn_commitment and after.weight_type == "int8" and after.evaluation == {}
    assert qnav(["export", str(new), "-o", str(new), "--turn-commitment", "--quiet"]) == 0
    assert PolicyRuntime(new).contract.turn_commitment
