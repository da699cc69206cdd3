"""Export a trained Q-network as one self-contained ONNX policy file with its contract.

The graph is the training network as the runtime steps it, `StreamingQNetwork`: the newest
frame and the carried partial windows in, Q values and the next partial windows out (the
window arithmetic of the training network, without recomputing the windows every step). It is
written by `torch.onnx.export` (the dynamo exporter, with graph optimisation off so that the
weights keep their parameter names: the numpy backend finds them by name). Weights are stored
inside the file. The metadata holds a `PolicyContract`; the file is then evaluated under the
test protocol through the onboard runtime and its results written in.

`reexport_file` turns a file of the earlier layout (qnav-policy/1, a graph over the whole
window) into the current one from the file's own weights, keeping its metadata.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import tempfile
import warnings
from collections.abc import Mapping
from dataclasses import asdict, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import onnx
import torch
from numpy.typing import NDArray

from qnav.contracts.errors import PolicyFileError
from qnav.contracts.motion import action_velocities
from qnav.contracts.observation import distance_scale_m
from qnav.contracts.policy_file import (
    FRAME_INPUT,
    METADATA_PREFIX,
    OUTPUT_NAME,
    POLICY_FORMAT,
    STATE_INPUTS,
    STATE_OUTPUTS,
    WINDOW_FORMAT,
    ActionVelocity,
    PolicyContract,
)
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalResult, StreamPolicy
from qnav.training.networks import QNetwork, StreamingQNetwork
from qnav.training.quantize import quantize_int8

REEXPORT_KEY = METADATA_PREFIX + "reexported_from"
"""Metadata entry (not part of the contract) that `reexport_file` leaves: what the weights were
taken from."""


def policy_contract(
    network: QNetwork,
    world: WorldConfig,
    window_length: int,
    training_run: str,
    commit: str,
    *,
    weight_type: str = "float32",
) -> PolicyContract:
    """The contract of `network` trained in `world` (no evaluation yet), its weights to be
    stored as `weight_type` (float32 or int8)."""
    velocities = action_velocities(world.dynamics, world.control_period_s)
    streaming = StreamingQNetwork(network, window_length)
    return PolicyContract(
        model_kind=network.kind,
        window_length=window_length,
        num_beams=network.num_beams,
        max_range_m=distance_scale_m(world.lidar),
        control_period_s=world.control_period_s,
        actions=tuple(ActionVelocity(linear, angular) for linear, angular in velocities),
        dynamics=world.dynamics.kind,
        scenario=world.name,
        training_run=training_run,
        commit=commit,
        state_slots=streaming.state_slots,
        state_size=streaming.state_size,
        weight_type=weight_type,
        motion=motion_of(world),
    )


def motion_of(world: WorldConfig) -> dict[str, Any]:
    """The contract's `motion` entry for a policy trained in `world`."""
    return {"dynamics": asdict(world.dynamics), "robot_radius_m": world.robot_radius_m}


def export_onnx(
    network: QNetwork,
    contract: PolicyContract,
    path: Path,
    extra_metadata: dict[str, str] | None = None,
) -> None:
    """Write `network` to `path` as one ONNX file (weights inside) carrying `contract`, its
    streaming form as the graph (`StreamingQNetwork`), with int8 weights if the contract says
    so (`training.quantize`); `extra_metadata` is written beside the contract's entries, in
    place of any the new model carries under the same key (the quantiser's `onnx.infer`)."""
    model = streaming_model(network, contract)
    if contract.weight_type == "int8":
        model = quantize_int8(model)
    write_metadata(model, contract)
    replace_metadata(model, extra_metadata or {})
    save_checked(model, path)


def save_checked(model: onnx.ModelProto, path: Path) -> None:
    """Check `model` with onnx's full checker and write it to `path` atomically, weights inside."""
    onnx.checker.check_model(model, full_check=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    onnx.save_model(model, tmp, save_as_external_data=False)
    tmp.replace(path)


def streaming_model(network: QNetwork, contract: PolicyContract) -> onnx.ModelProto:
    """The ONNX model of `network` stepped as the runtime steps it (no metadata yet)."""
    streaming = StreamingQNetwork(network.eval().float(), contract.window_length).eval()
    if (streaming.state_slots, streaming.state_size) != (contract.state_slots, contract.state_size):
        raise ValueError(
            f"the contract's state ({contract.state_slots}, {contract.state_size}) is not the "
            f"network's ({streaming.state_slots}, {streaming.state_size})"
        )
    # An example batch of 2: with 1, torch.export fixes the batch axis of the state inputs to 1.
    batch = torch.export.Dim("batch", min=1, max=65536)
    inputs = {"frame": torch.zeros(2, contract.frame_size)}
    output_names = [OUTPUT_NAME]
    if contract.has_state:
        shape = (2, contract.state_slots, contract.state_size)
        inputs |= {"state_h": torch.zeros(shape), "state_c": torch.zeros(shape)}
        output_names += list(STATE_OUTPUTS)
    program = quiet_export(
        streaming,
        inputs,
        input_names=[FRAME_INPUT, *STATE_INPUTS][: len(inputs)],
        output_names=output_names,
        dynamic_shapes={name: {0: batch} for name in inputs},
    )
    model = program.model_proto
    model.doc_string = _graph_description(contract)
    return model


def _graph_description(contract: PolicyContract) -> str:
    inputs = f"'{FRAME_INPUT}' (batch, {contract.frame_size}), the newest encoded frame"
    outputs = (
        f"'{OUTPUT_NAME}' (batch, 3), Q values of forward, left, right for the window of the "
        f"last {contract.window_length} frames"
    )
    if contract.has_state:
        inputs += (
            f"; '{STATE_INPUTS[0]}', '{STATE_INPUTS[1]}' (batch, {contract.state_slots}, "
            f"{contract.state_size}), the LSTM state of the windows in progress"
        )
        outputs += f"; '{STATE_OUTPUTS[0]}', '{STATE_OUTPUTS[1]}', the state for the next frame"
    return (
        f"qnav {contract.model_kind} Q-network for {contract.scenario}, one step per frame. "
        f"Inputs: {inputs}. Outputs: {outputs}."
    )


def quiet_export(
    module: torch.nn.Module,
    inputs: dict[str, torch.Tensor],
    *,
    input_names: list[str],
    output_names: list[str],
    dynamic_shapes: dict[str, dict[int, torch.export.Dim]],
) -> torch.onnx.ONNXProgram:
    """`torch.onnx.export` (dynamo, weights inside, names kept), without its narration."""
    # The exporter narrates every stage and warns about optional packages; keep the CLI quiet.
    quiet = logging.getLogger("torch.onnx")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(
                module,
                (),
                kwargs=inputs,
                dynamo=True,
                external_data=False,
                optimize=False,
                input_names=input_names,
                output_names=output_names,
                dynamic_shapes=dynamic_shapes,
            )
    finally:
        quiet.setLevel(level)
    assert program is not None
    return program


class HasMetadata(Protocol):
    """A file's contract (`PolicyContract`)."""

    def to_metadata(self) -> dict[str, str]: ...


def write_metadata(model: onnx.ModelProto, contract: HasMetadata) -> None:
    """Replace the model's qnav metadata with `contract`."""
    replace_metadata(model, contract.to_metadata())


def replace_metadata(model: onnx.ModelProto, entries: dict[str, str]) -> None:
    """Set the model's metadata `entries`, in place of any it has under the same keys."""
    kept = [p for p in model.metadata_props if p.key not in entries]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    for key, value in entries.items():
        model.metadata_props.add(key=key, value=value)


def set_evaluation(path: Path, evaluation: dict[str, float]) -> PolicyContract:
    """Record test-protocol results in the file's metadata (the weights stay as they are)."""
    from qnav.controller.onnx_file import read_onnx

    contract = PolicyContract.from_metadata(read_onnx(path).metadata, str(path))
    contract = replace(contract, evaluation=evaluation)
    model = onnx.load_model(path)
    write_metadata(model, contract)
    tmp = path.with_name(path.name + ".partial")
    onnx.save_model(model, tmp, save_as_external_data=False)
    tmp.replace(path)
    return contract


def torch_q_values(network: QNetwork, frames: NDArray[np.float32]) -> NDArray[np.float32]:
    """The torch network's Q values for windows (N, k, F), in float32 on the CPU."""
    with torch.no_grad():
        q: NDArray[np.float32] = network.eval()(torch.from_numpy(frames)).numpy()
    return q


def evaluation_summary(result: EvalResult) -> dict[str, float]:
    """The fractions and episode count of an EvalResult, as stored in metadata."""
    values = asdict(result)
    return {k: float(values[k]) for k in ("success", "collision", "unfinished", "episodes")}


def export_run(
    run_dir: Path,
    output: Path,
    *,
    eval_episodes: int = 200,
    backend: str = "onnxruntime",
    weight_type: str = "float32",
    progress: bool = True,
    weights: Path | None = None,
    turn_commitment: bool | None = None,
) -> PolicyContract:
    """Export a training run's network (from `weights`, by default its final one) to `output`
    (weights in `weight_type`; the contract's `turn_commitment` as given, by default the
    run's), then test the file itself and record it."""
    from qnav.training.run_folder import load_network, source_commit

    network, run = load_network(run_dir, weights)
    results_path = run_dir / "results.json"
    commit = json.loads(results_path.read_text()).get("commit", "") if results_path.exists() else ""
    contract = policy_contract(
        network,
        run.world,
        run.train.window,
        str(run_dir),
        commit or source_commit(),
        weight_type=weight_type,
    )
    if turn_commitment is None:
        turn_commitment = run.train.imitation.turn_commitment
    contract = replace(contract, turn_commitment=turn_commitment)
    export_onnx(network, contract, output)
    if eval_episodes <= 0:
        return contract
    return evaluate_export(
        network,
        contract,
        output,
        run.world,
        episodes=eval_episodes,
        backend=backend,
        progress=progress,
    )


def evaluate_export(
    network: QNetwork,
    contract: PolicyContract,
    path: Path,
    world: WorldConfig,
    *,
    episodes: int,
    backend: str,
    progress: bool,
) -> PolicyContract:
    """Test the file `network` was exported to (`contract`); an int8 file is run beside the
    float32 export of the same network, which sees the same observations, and the share of
    decisions where the two agree is recorded too."""
    if contract.weight_type == "float32":
        return evaluate_file(path, world, episodes=episodes, backend=backend, progress=progress)
    with tempfile.TemporaryDirectory() as scratch:
        reference = Path(scratch) / "float32.onnx"
        export_onnx(network, replace(contract, weight_type="float32"), reference)
        return evaluate_file(
            path, world, episodes=episodes, backend=backend, progress=progress, reference=reference
        )


def evaluate_file(
    path: Path,
    world: WorldConfig,
    *,
    episodes: int,
    backend: str,
    progress: bool,
    reference: Path | None = None,
) -> PolicyContract:
    """Run the test protocol on the policy file itself (through the onboard runtime) in
    `world` and record the results in its metadata; with a `reference` policy file, also the
    share of the file's decisions that the reference takes too (`agreement_with_float32`)."""
    from qnav.controller.policy import PolicyRuntime
    from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent, evaluate

    settings = EvalSettings(episodes=episodes)
    worlds = min(settings.num_worlds, episodes)

    def runtime(file: Path) -> PolicyRuntime:
        return PolicyRuntime(file, backend=backend, num_streams=worlds)  # type: ignore[arg-type]

    acting = runtime(path)
    policy = acting if reference is None else AgreementPolicy(acting, runtime(reference))
    result = evaluate(world, StreamPolicyAgent(policy, worlds), settings, progress=progress)
    summary = evaluation_summary(result)
    if isinstance(policy, AgreementPolicy):
        summary[AGREEMENT_KEY] = policy.agreement()
    return set_evaluation(path, summary)


AGREEMENT_KEY = "agreement_with_float32"
"""Evaluation entry of an int8 file: the share of its test decisions the float32 network takes."""


class AgreementPolicy:
    """Acts as `acting` and counts how often `reference`, fed the same observations, picks the
    same action (a `sim.evaluate.StreamPolicy`)."""

    def __init__(self, acting: StreamPolicy, reference: StreamPolicy) -> None:
        self.acting, self.reference = acting, reference
        self.decisions = self.agreed = 0

    def reset(self, streams: NDArray[np.intp] | None = None) -> None:
        self.acting.reset(streams)
        self.reference.reset(streams)

    def step_batch(
        self, scan_m: NDArray[np.floating] | None, target_features: NDArray[np.floating]
    ) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
        actions, q = self.acting.step_batch(scan_m, target_features)
        expected, _ = self.reference.step_batch(scan_m, target_features)
        self.decisions += actions.size
        self.agreed += int(np.count_nonzero(actions == expected))
        return actions, q

    def agreement(self) -> float:
        """Share of decisions so far where the two picked the same action."""
        return self.agreed / max(self.decisions, 1)


def reexport_file(
    source: Path,
    output: Path,
    *,
    eval_episodes: int = 0,
    backend: str = "onnxruntime",
    weight_type: str | None = None,
    progress: bool = True,
    turn_commitment: bool | None = None,
) -> PolicyContract:
    """Export a policy file again, in this version's layout, from its own weights.

    The file's initializers carry the training network's parameter names, so the QNetwork is
    rebuilt from them (its sizes read off the weights; int8 weights dequantised) and exported
    as `export_onnx` exports a run's, its weights stored as `weight_type` (None: as in the
    source). Every metadata entry is kept (training run, commit, evaluation...) apart from the
    format and the state's shape, which the new graph defines, and the evaluation when the
    weight type or `turn_commitment` (None: as in the source) changes; a
    `qnav.reexported_from` entry says what the weights came from. With
    `eval_episodes` > 0 the new file is evaluated under the test protocol in its scenario's
    default world and the results replace the old ones.
    """
    from qnav.controller.onnx_file import float_weights, read_onnx
    from qnav.sim.config import scenario

    contents = read_onnx(source)
    metadata = dict(contents.metadata)
    found = json.loads(metadata.get(METADATA_PREFIX + "format", "null"))
    if found not in (WINDOW_FORMAT, POLICY_FORMAT):
        raise PolicyFileError(
            f"{source} has policy format {found!r}; re-export reads {WINDOW_FORMAT!r} and "
            f"{POLICY_FORMAT!r} files"
        )
    kind = json.loads(metadata[METADATA_PREFIX + "model_kind"])
    beams = json.loads(metadata[METADATA_PREFIX + "num_beams"])
    window = json.loads(metadata[METADATA_PREFIX + "window_length"])
    # With a window of one frame the graph never reads the recurrent matrix, so the exporter
    # left it out: any value rebuilds the same policy.
    unused = {"lstm.weight_hh_l0"} if kind == "recurrent" and window == 1 else set()
    network = network_from_weights(float_weights(contents.initializers), kind, beams, unused)
    streaming = StreamingQNetwork(network, window)
    metadata |= {
        METADATA_PREFIX + "format": json.dumps(POLICY_FORMAT),
        METADATA_PREFIX + "state_slots": json.dumps(streaming.state_slots),
        METADATA_PREFIX + "state_size": json.dumps(streaming.state_size),
    }
    source_contract = PolicyContract.from_metadata(metadata, str(source))
    contract = source_contract
    if weight_type is not None and weight_type != source_contract.weight_type:
        contract = replace(source_contract, weight_type=weight_type, evaluation={})
    if turn_commitment is not None and turn_commitment != contract.turn_commitment:
        contract = replace(contract, turn_commitment=turn_commitment, evaluation={})
    if not contract.motion:  # a file from before the entry: its scenario's default world
        contract = replace(contract, motion=motion_of(scenario(contract.scenario)))
    note = {
        "file": str(source),
        "format": found,
        "sha256": hashlib.sha256(source.read_bytes()).hexdigest(),
        "date": datetime.now(UTC).date().isoformat(),
        "by": "qnav export FILE.onnx (training.export.reexport_file)",
        "weights": "the file's own initializers, unchanged"
        if source_contract.weight_type == "float32"
        else "the file's own int8 initializers, dequantised",
    }
    extra = {k: v for k, v in metadata.items() if k not in contract.to_metadata()}
    export_onnx(network, contract, output, extra | {REEXPORT_KEY: json.dumps(note)})
    if eval_episodes <= 0:
        return contract
    world = scenario(contract.scenario)
    return evaluate_export(
        network, contract, output, world, episodes=eval_episodes, backend=backend, progress=progress
    )


def network_from_weights(
    weights: Mapping[str, NDArray[np.generic]],
    kind: str,
    num_beams: int,
    unused: set[str] | None = None,
) -> QNetwork:
    """The QNetwork whose parameters are `weights` (by parameter name; every one required but
    those in `unused`, which the policy never reads and which are set to zero)."""
    if "head.0.weight" not in weights:
        raise PolicyFileError("the policy file has no weight 'head.0.weight'")
    hidden_size = int(weights["head.0.weight"].shape[0])
    network = QNetwork(kind, num_beams or None, hidden_size)  # type: ignore[arg-type]
    expected = network.state_dict()
    missing = sorted(set(expected) - weights.keys() - (unused or set()))
    if missing:
        raise PolicyFileError(f"the policy file lacks the weights {', '.join(missing)}")
    state = {
        name: torch.from_numpy(np.array(weights[name], dtype=np.float32))
        if name in weights
        else torch.zeros_like(value)
        for name, value in expected.items()
    }
    network.load_state_dict(state, strict=True)
    return network.eval()
