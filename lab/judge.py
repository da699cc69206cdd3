"""A label folder's doom judgement as a file the controller runs (`contracts.judge_file`).

`qnav lab label FOLDER ... --test-episodes N --export FILE` writes the folder's latest fit
(`lab.doubt`, the obstacle-set network on the contract's obstacle slots) with the threshold its
final test chose on validation layouts and the test's figures. The graph is the fit itself,
exported as `training.export` exports policies (dynamo, weights inside under the network's
parameter names, which the controller's numpy backend reads); the file is checked against the
fit through onnxruntime before it is kept.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch

from qnav.contracts.errors import PolicyFileError
from qnav.contracts.judge_file import (
    CONTEXT_FEATURES,
    CONTEXT_INPUT,
    OBSTACLES_INPUT,
    OUTPUT_NAME,
    JudgeContract,
)
from qnav.contracts.observation import OBSTACLE_SLOT_FEATURES, OBSTACLE_SLOTS, distance_scale_m
from qnav.lab.doubt import FinalTest
from qnav.lab.oracle import DOOM_HORIZON_S
from qnav.sim.config import WorldConfig
from qnav.training.export import quiet_export, save_checked, write_metadata
from qnav.training.run_folder import source_commit

CHECK_TOLERANCE = 1e-4
"""Largest difference in P(safe) between the fit and its file allowed at export."""


def judge_contract(
    world: WorldConfig, test: FinalTest, training: dict[str, Any], commit: str = ""
) -> JudgeContract:
    """The contract of a fit labelled in `world` whose final test is `test`; `training` says
    where its labels came from."""
    return JudgeContract(
        scenario=world.name,
        dynamics=world.dynamics.kind,
        control_period_s=world.control_period_s,
        max_range_m=distance_scale_m(world.lidar),
        threshold=test.threshold,
        horizon_s=DOOM_HORIZON_S,
        training=training,
        evaluation={
            "success": test.truth.success,
            "tracked_success": test.tracked.success,
            "tracked_noisy_success": test.tracked_noisy.success,
            "episodes": test.truth.episodes,
        },
        commit=commit or source_commit(),
    )


def judge_model(network: torch.nn.Module, contract: JudgeContract) -> onnx.ModelProto:
    """The ONNX model of the fit, with the contract in its metadata."""
    batch = torch.export.Dim("batch", min=1, max=65536)
    inputs = {
        CONTEXT_INPUT: torch.zeros(2, CONTEXT_FEATURES),
        OBSTACLES_INPUT: torch.zeros(2, OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES),
    }
    program = quiet_export(
        network.eval().float(),
        inputs,
        input_names=list(inputs),
        output_names=[OUTPUT_NAME],
        dynamic_shapes={name: {0: batch} for name in inputs},
    )
    model = program.model_proto
    model.doc_string = (
        f"qnav doom judge for {contract.scenario}: inputs '{CONTEXT_INPUT}' (batch, "
        f"{CONTEXT_FEATURES}) and '{OBSTACLES_INPUT}' (batch, {OBSTACLE_SLOTS}, "
        f"{OBSTACLE_SLOT_FEATURES}); output '{OUTPUT_NAME}' (batch, 3), the logit that each "
        f"action is safe; keep the policy's action where P(safe) > {contract.threshold}."
    )
    write_metadata(model, contract)
    return model


def export_judge(network: torch.nn.Module, contract: JudgeContract, path: Path) -> None:
    """Write the fit to `path` as a doom judge file, after checking that onnxruntime gives the
    fit's P(safe) on a seeded batch of inputs (PolicyFileError otherwise)."""
    from qnav.controller.judge import DoomJudge

    model = judge_model(network, contract)
    partial = path.with_name(path.name + ".check")
    save_checked(model, partial)
    try:
        random = np.random.default_rng(0)
        context = random.normal(size=(64, CONTEXT_FEATURES)).astype(np.float32)
        shape = (64, OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES)
        obstacles = random.normal(size=shape).astype(np.float32)
        with torch.no_grad():
            expected = torch.sigmoid(
                network(torch.from_numpy(context), torch.from_numpy(obstacles))
            ).numpy()
        found = DoomJudge(partial).safe_probability(context, obstacles)
        difference = float(np.abs(found - expected).max())
        if difference > CHECK_TOLERANCE:
            raise PolicyFileError(
                f"the exported judge differs from the fit by {difference:.2g} in P(safe) "
                f"(allowed {CHECK_TOLERANCE})"
            )
        partial.replace(path)
    finally:
        partial.unlink(missing_ok=True)
