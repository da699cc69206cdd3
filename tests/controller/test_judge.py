"""The onboard doom judge: the file gives the fit's judgement on both backends, and the
controller refuses a judge that does not fit its policy or its settings, naming why."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from qnav.contracts.errors import ConfigError, PolicyFileError
from qnav.contracts.judge_file import CONTEXT_FEATURES
from qnav.contracts.observation import OBSTACLE_SLOT_FEATURES, OBSTACLE_SLOTS
from qnav.controller.decision import Controller
from qnav.controller.judge import DoomJudge
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.policy import BACKENDS, Backend, PolicyRuntime
from tests.conftest import JUDGE_THRESHOLD, judge_network

DATA = Path(__file__).parents[1] / "data" / "stack"
OBSTACLES_POLICY = DATA / "obstacles-inertia.onnx"


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_judge_file_gives_the_fits_safe_probability(
    backend: Backend, make_judge: Callable[[str], Path]
) -> None:
    random = np.random.default_rng(3)
    context = random.normal(size=(50, CONTEXT_FEATURES)).astype(np.float32)
    shape = (50, OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES)
    obstacles = random.normal(size=shape).astype(np.float32)
    with torch.no_grad():
        fit = judge_network()(torch.from_numpy(context), torch.from_numpy(obstacles))
    expected = torch.sigmoid(fit).numpy()
    judge = DoomJudge(make_judge("obstacles-inertia"), backend)
    np.testing.assert_allclose(judge.safe_probability(context, obstacles), expected, atol=1e-6)
    assert judge.contract.threshold == JUDGE_THRESHOLD


def test_a_judge_of_other_dynamics_than_the_policys_is_refused_naming_both(
    make_judge: Callable[[str], Path],
) -> None:
    judge = make_judge("obstacles-increment")
    settings = LookaheadSettings(mode="judge", judge_file=str(judge), room_size_m=10.0)
    with pytest.raises(PolicyFileError, match=r"increment dynamics.*drives inertia"):
        Controller(PolicyRuntime(OBSTACLES_POLICY), lookahead=settings)


def test_a_policy_file_given_as_the_judge_is_refused_naming_the_fix() -> None:
    settings = LookaheadSettings(mode="judge", judge_file=str(OBSTACLES_POLICY), room_size_m=10.0)
    with pytest.raises(PolicyFileError, match=r"not a qnav doom judge.*--export"):
        Controller(PolicyRuntime(OBSTACLES_POLICY), lookahead=settings)


def test_mode_judge_without_a_file_and_a_file_without_mode_judge_name_the_setting() -> None:
    with pytest.raises(ConfigError, match=r"lookahead\.judge_file"):
        LookaheadSettings(mode="judge")
    with pytest.raises(ConfigError, match=r"lookahead\.judge_file"):
        LookaheadSettings(mode="shield", judge_file="judge.onnx")


def test_a_missing_judge_file_is_refused_by_name() -> None:
    settings = LookaheadSettings(mode="judge", judge_file="nowhere/judge.onnx", room_size_m=10.0)
    with pytest.raises(PolicyFileError, match=r"doom judge file nowhere/judge\.onnx does not"):
        Controller(PolicyRuntime(OBSTACLES_POLICY), lookahead=settings)
