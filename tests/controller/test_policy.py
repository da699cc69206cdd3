"""The onboard policy runtime: refuses what is not ours or does not fit, never returns NaN, and
its streaming decisions are the window network's."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
import pytest

from qnav.contracts.actions import committed_turns
from qnav.contracts.errors import PolicyFileError, PolicyInputError
from qnav.contracts.observation import FrameWindow
from qnav.controller.policy import BACKENDS, Expectation, PolicyRuntime
from tests.conftest import PolicyFactory, policy_network, with_metadata
from tests.near_ties import assert_actions_match_but_near_ties

BEAMS = 720
BARN_POLICY = Path(__file__).parents[2] / "results" / "barn" / "barn-recurrent.onnx"


@pytest.fixture(params=["onnxruntime", "numpy"])
def runtime(request: pytest.FixtureRequest, make_policy: PolicyFactory) -> PolicyRuntime:
    return PolicyRuntime(make_policy("walls-inertia"), backend=request.param)


def _features() -> np.ndarray:
    return np.array([2.0, 0.6, 0.8])


def test_a_file_that_is_not_onnx_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "junk.onnx"
    path.write_bytes(b"\xff" * 64)
    with pytest.raises(PolicyFileError, match=r"junk\.onnx"):
        PolicyRuntime(path)


def test_an_onnx_model_without_our_metadata_is_not_a_policy(tmp_path: Path) -> None:
    graph = onnx.helper.make_graph(
        [onnx.helper.make_node("Identity", ["x"], ["y"])],
        "plain",
        [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
        [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])],
    )
    path = tmp_path / "plain.onnx"
    onnx.save(onnx.helper.make_model(graph), str(path))
    with pytest.raises(PolicyFileError, match="not a qnav policy"):
        PolicyRuntime(path)


def test_a_missing_metadata_entry_is_named(make_policy: PolicyFactory, tmp_path: Path) -> None:
    model = onnx.load(str(make_policy("walls-inertia")))
    kept = [p for p in model.metadata_props if p.key != "qnav.window_length"]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    path = tmp_path / "incomplete.onnx"
    onnx.save(model, str(path))
    with pytest.raises(PolicyFileError, match=r"qnav\.window_length"):
        PolicyRuntime(path)


def test_a_file_of_the_earlier_window_layout_is_refused_with_the_fix_named(
    make_policy: PolicyFactory, tmp_path: Path
) -> None:
    path = with_metadata(
        make_policy("walls-inertia"), tmp_path / "window.onnx", {"qnav.format": "qnav-policy/1"}
    )
    for backend in BACKENDS:
        with pytest.raises(PolicyFileError, match=r"qnav-policy/1.*Re-export it: `qnav export"):
            PolicyRuntime(path, backend=backend)


def test_an_unknown_weight_type_is_refused_naming_it(
    make_policy: PolicyFactory, tmp_path: Path
) -> None:
    source = make_policy("walls-inertia")
    path = with_metadata(source, tmp_path / "int4.onnx", {"qnav.weight_type": "int4"})
    with pytest.raises(PolicyFileError, match=r"weight_type = 'int4'.*float32, int8"):
        PolicyRuntime(path)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_policy_whose_action_velocity_is_not_finite_is_refused_at_load(
    make_policy: PolicyFactory, tmp_path: Path, bad: float
) -> None:
    """JSON metadata read by Python takes NaN and Infinity: such a velocity would be published
    as a command (the bridge refuses it, but the controller must not send it)."""
    actions = [
        {"linear_mps": 0.5, "angular_radps": 0.0},
        {"linear_mps": 0.1, "angular_radps": bad},
        {"linear_mps": 0.1, "angular_radps": -1.0},
    ]
    path = with_metadata(
        make_policy("walls-inertia"), tmp_path / "nan.onnx", {"qnav.actions": actions}
    )
    with pytest.raises(PolicyFileError, match=r"qnav\.actions .*not finite: left = "):
        PolicyRuntime(path)


@pytest.mark.parametrize(
    ("expect", "named"),
    [
        (Expectation(num_beams=360), "num_beams is 720 in the file but 360 here"),
        (Expectation(window_length=8), "window_length is 5 in the file but 8 here"),
        (Expectation(num_beams=0), "num_beams is 720 in the file but 0 here"),
    ],
)
def test_a_policy_that_does_not_fit_the_inputs_is_refused_at_load(
    make_policy: PolicyFactory, expect: Expectation, named: str
) -> None:
    with pytest.raises(PolicyFileError, match=named):
        PolicyRuntime(make_policy("walls-inertia"), expect=expect)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -3.0, 1e30])
def test_non_finite_or_negative_ranges_never_give_nan_q_values(
    runtime: PolicyRuntime, bad: float
) -> None:
    scan = np.full(BEAMS, 3.0, dtype=np.float32)
    scan[::7] = bad
    decision = runtime.step(scan, _features())
    assert np.isfinite(decision.q_values).all()


def test_no_return_reads_as_maximum_range_and_negative_as_zero(runtime: PolicyRuntime) -> None:
    max_range = runtime.contract.max_range_m
    as_inf = runtime.encode(np.full((1, BEAMS), np.inf), _features()[None])
    as_max = runtime.encode(np.full((1, BEAMS), max_range), _features()[None])
    np.testing.assert_array_equal(as_inf, as_max)
    as_negative = runtime.encode(np.full((1, BEAMS), -1.0), _features()[None])
    assert (as_negative[0, :BEAMS] == 0.0).all()


@pytest.mark.parametrize("beams", [0, 360, 721])
def test_a_scan_of_the_wrong_length_is_refused(runtime: PolicyRuntime, beams: int) -> None:
    with pytest.raises(PolicyInputError, match="720 beams"):
        runtime.step(np.ones(beams), _features())


def test_non_finite_target_features_are_refused(runtime: PolicyRuntime) -> None:
    with pytest.raises(PolicyInputError, match="NaN or inf"):
        runtime.step(np.ones(BEAMS), np.array([np.nan, 0.0, 1.0]))


def test_the_window_restarts_padded_with_the_first_frame(runtime: PolicyRuntime) -> None:
    near, far = np.full(BEAMS, 1.0), np.full(BEAMS, 9.0)
    first = runtime.step(near, _features())
    for _ in range(4):
        runtime.step(far, _features())
    runtime.reset()
    again = runtime.step(near, _features())
    np.testing.assert_allclose(again.q_values, first.q_values, rtol=0, atol=1e-6)
    padded = np.repeat(runtime.encode(near[None], _features()[None])[:, None], 5, axis=1)
    np.testing.assert_allclose(
        again.q_values, runtime.window_q_values(padded)[0], rtol=0, atol=1e-6
    )


@pytest.mark.parametrize("backend", ["onnxruntime", "numpy"])
@pytest.mark.parametrize(
    ("scenario", "kind"),
    [
        ("walls-inertia", "recurrent"),
        ("walls-inertia", "feedforward"),
        ("toycar-inertia", "recurrent"),
    ],
)
def test_streaming_decisions_with_resets_equal_the_window_networks(
    make_policy: PolicyFactory, backend: str, scenario: str, kind: str
) -> None:
    """A long random sequence, streams restarting at random (one or several at once, all at
    once, one stream on consecutive steps): every decision is the torch window network's on
    the window `FrameWindow` keeps."""
    import torch

    world, network = policy_network(scenario, kind, 64, 0)
    streams, steps = 6, 400
    runtime = PolicyRuntime(
        make_policy(scenario, kind, 64),
        backend=backend,  # type: ignore[arg-type]
        num_streams=streams,
    )
    window = FrameWindow(streams, network.frame_size, 5)
    rng = np.random.default_rng(3)
    beams = world.lidar.num_beams if world.lidar else 0
    worst, restarts, near_ties = 0.0, 0, 0
    for t in range(steps):
        scans = rng.uniform(0.0, 25.0, size=(streams, beams)) if beams else None
        bearing = rng.uniform(-np.pi, np.pi, streams)
        features = np.stack([rng.uniform(0, 8, streams), np.sin(bearing), np.cos(bearing)], 1)
        actions, q = runtime.step_batch(scans, features)
        windows = window.advance(runtime.encode(scans, features))
        with torch.no_grad():
            expected = network(torch.from_numpy(windows)).numpy()
        near_ties += assert_actions_match_but_near_ties(actions, expected, f"step {t}")
        worst = max(worst, float(np.abs(q - expected).max()))
        restart = (
            np.arange(streams)
            if t % 97 == 50
            else np.array([1])
            if t in (10, 11, 12)
            else np.flatnonzero(rng.random(streams) < 0.08)
        )
        runtime.reset(restart)
        window.restart(restart)
        restarts += restart.size
    assert worst <= 1e-4
    assert restarts > 150
    assert near_ties <= streams * steps // 100  # rare: exact equality but for rounding


def test_the_lidarless_policy_takes_pose_and_target_only(make_policy: PolicyFactory) -> None:
    runtime = PolicyRuntime(make_policy("toycar-inertia"), expect=Expectation(num_beams=0))
    decision = runtime.step(None, _features())
    assert np.isfinite(decision.q_values).all()
    with pytest.raises(PolicyInputError, match="no lidar"):
        runtime.step(np.ones(BEAMS), _features())


def test_with_turn_commitment_a_stream_never_reverses_a_turn_until_it_drives_forward(
    tmp_path: Path,
) -> None:
    from qnav.sim.config import scenario
    from qnav.sim.world import observe, reset, step

    committed = with_metadata(BARN_POLICY, tmp_path / "c.onnx", {"qnav.turn_commitment": True})
    world, streams = scenario("cave"), 64
    runtime = PolicyRuntime(committed, num_streams=streams)
    assert runtime.contract.turn_commitment
    state = reset(world, np.zeros(streams, dtype=np.int64), np.arange(streams))
    previous = np.zeros(streams, dtype=np.int64)  # an episode starts as after a forward decision
    reversals = 0
    for _ in range(60):
        observation = observe(world, state)
        actions, q = runtime.step_batch(observation.scan_m, observation.target_features())
        expected = committed_turns(q.argmax(axis=1), previous)
        reversals += int(np.sum(expected != q.argmax(axis=1)))
        assert actions.tolist() == expected.tolist()
        state, _, transition = step(world, state, actions)
        done = np.flatnonzero(transition.terminated | transition.truncated)
        runtime.reset(done)
        actions[done] = 0
        previous = actions
    assert reversals > 0  # the greedy choices did reverse turns, and the runtime kept them
