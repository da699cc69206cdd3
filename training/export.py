"""Export a trained Q-network as one self-contained ONNX policy file with its contract.

The graph is the training network itself (`torch.onnx.export`, the dynamo exporter, with graph
optimisation off so that the weights keep their parameter names: the numpy backend finds them
by name). Weights are stored inside the file. The metadata holds a `PolicyContract`; the file is
then evaluated under the test protocol through the onboard runtime and its results written in.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import warnings
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import onnx
import torch
from numpy.typing import NDArray

from contracts.observation import distance_scale_m
from contracts.policy_file import (
    INPUT_NAME,
    OUTPUT_NAME,
    ActionVelocity,
    PolicyContract,
)
from sim.config import WorldConfig
from sim.dynamics import action_velocities
from sim.evaluate import EvalResult
from training.networks import QNetwork


def policy_contract(
    network: QNetwork,
    world: WorldConfig,
    window_length: int,
    training_run: str,
    commit: str,
) -> PolicyContract:
    """The contract of `network` trained in `world` (no evaluation yet)."""
    velocities = action_velocities(world.dynamics, world.control_period_s)
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
    )


def export_onnx(network: QNetwork, contract: PolicyContract, path: Path) -> None:
    """Write `network` to `path` as one ONNX file (weights inside) carrying `contract`."""
    example = torch.zeros(1, contract.window_length, contract.frame_size)
    network = network.eval().float()
    path.parent.mkdir(parents=True, exist_ok=True)
    # The exporter narrates every stage and warns about optional packages; keep the CLI quiet.
    quiet = logging.getLogger("torch.onnx")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(
                network,
                (example,),
                dynamo=True,
                external_data=False,
                optimize=False,
                input_names=[INPUT_NAME],
                output_names=[OUTPUT_NAME],
                dynamic_shapes={"frames": {0: torch.export.Dim("batch", min=1, max=65536)}},
            )
    finally:
        quiet.setLevel(level)
    assert program is not None
    model = program.model_proto
    model.doc_string = (
        f"qnav {contract.model_kind} Q-network for {contract.scenario}: input '{INPUT_NAME}' "
        f"(batch, {contract.window_length}, {contract.frame_size}) encoded frames, output "
        f"'{OUTPUT_NAME}' (batch, 3) Q values of forward, left, right"
    )
    write_metadata(model, contract)
    onnx.checker.check_model(model, full_check=True)
    tmp = path.with_name(path.name + ".partial")
    onnx.save_model(model, tmp, save_as_external_data=False)
    tmp.replace(path)


def write_metadata(model: onnx.ModelProto, contract: PolicyContract) -> None:
    """Replace the model's qnav metadata with `contract`."""
    kept = [p for p in model.metadata_props if p.key not in contract.to_metadata()]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    for key, value in contract.to_metadata().items():
        model.metadata_props.add(key=key, value=value)


def set_evaluation(path: Path, evaluation: dict[str, float]) -> PolicyContract:
    """Record test-protocol results in the file's metadata (the weights stay as they are)."""
    from controller.onnx_file import read_onnx

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
    progress: bool = True,
) -> PolicyContract:
    """Export a training run's network to `output`, then test the file itself and record it."""
    from controller.policy import PolicyRuntime
    from sim.evaluate import EvalSettings, StreamPolicyAgent, evaluate
    from training.policy import load_network
    from training.run import source_commit

    network, run = load_network(run_dir)
    results_path = run_dir / "results.json"
    commit = json.loads(results_path.read_text()).get("commit", "") if results_path.exists() else ""
    contract = policy_contract(
        network, run.world, run.train.window, str(run_dir), commit or source_commit()
    )
    export_onnx(network, contract, output)
    if eval_episodes <= 0:
        return contract
    settings = EvalSettings(episodes=eval_episodes)
    worlds = min(settings.num_worlds, eval_episodes)
    runtime = PolicyRuntime(output, backend=backend, num_streams=worlds)  # type: ignore[arg-type]
    result = evaluate(run.world, StreamPolicyAgent(runtime, worlds), settings, progress=progress)
    return set_evaluation(output, evaluation_summary(result))
