"""The doom judge file's contract: its metadata, its inputs and the rule its threshold is for."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from qnav.contracts.errors import PolicyFileError
from qnav.contracts.judge_file import (
    CONTEXT_FEATURES,
    JUDGE_FORMAT,
    JudgeContract,
    judge_inputs,
    judged_actions,
)
from qnav.contracts.observation import OBSTACLE_FEATURES, OBSTACLE_SLOT_FEATURES, OBSTACLE_SLOTS

CONTRACT = JudgeContract(
    scenario="obstacles-inertia",
    dynamics="inertia",
    control_period_s=0.2,
    max_range_m=5.0,
    threshold=0.9,
    horizon_s=4.0,
    training={"folder": "runs/label/x", "rounds": 6},
    evaluation={"success": 0.839, "episodes": 1000},
    commit="abc",
)


def test_a_judge_keeps_the_preferred_action_where_judged_safe_else_takes_the_safest() -> None:
    preferred = np.array([0, 1, 2, 2])
    safe = np.array(
        [
            [0.9, 0.1, 0.1],  # judged safe: kept
            [0.2, 0.4, 0.8],  # judged doomed: the safest instead
            [0.7, 0.9, 0.51],  # judged safe, although others are safer: kept
            [0.6, 0.2, 0.5],  # exactly 1/2 is not safe
        ]
    )
    np.testing.assert_array_equal(judged_actions(preferred, safe, 0.5), [0, 2, 2, 0])
    # a stricter judge keeps the preferred action only where surer of it
    np.testing.assert_array_equal(judged_actions(preferred, safe, 0.8), [0, 2, 1, 0])


def test_the_contract_reads_back_from_its_metadata_exactly() -> None:
    assert JudgeContract.from_metadata(CONTRACT.to_metadata(), "judge.onnx") == CONTRACT


def test_a_policy_file_or_a_file_missing_an_entry_is_refused_by_name() -> None:
    policy_like = CONTRACT.to_metadata() | {"qnav.format": '"qnav-policy/2"'}
    with pytest.raises(PolicyFileError, match=f"not a qnav doom judge.*{JUDGE_FORMAT}"):
        JudgeContract.from_metadata(policy_like, "policy.onnx")
    partial = CONTRACT.to_metadata()
    del partial["qnav.threshold"]
    with pytest.raises(PolicyFileError, match=r"lacks the metadata entry 'qnav\.threshold'"):
        JudgeContract.from_metadata(partial, "judge.onnx")


def test_a_threshold_outside_zero_to_one_is_refused() -> None:
    with pytest.raises(PolicyFileError, match=r"threshold = 1\.0"):
        replace(CONTRACT, threshold=1.0)


def test_judge_inputs_are_the_velocity_and_target_then_one_row_per_obstacle_slot() -> None:
    velocity = np.array([[0.5, -0.1]])
    target = np.array([[0.4, 0.0, 1.0]])
    obstacles = np.arange(OBSTACLE_FEATURES, dtype=np.float32)[None]
    context, slots = judge_inputs(velocity, target, obstacles)
    assert context.shape == (1, CONTEXT_FEATURES) and context.dtype == np.float32
    np.testing.assert_allclose(context[0], [0.5, -0.1, 0.4, 0.0, 1.0])
    assert slots.shape == (1, OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES)
    np.testing.assert_array_equal(slots[0, 1], np.arange(5, 10))
