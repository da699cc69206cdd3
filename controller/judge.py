"""The onboard doom judge: a learned judgement of which actions are doomed, from what the car
perceives (`contracts.judge_file`; docs/controller.md, "The learned doom judge").

`lookahead.mode = "judge"` asks it at every decision instead of forecasting: the car's own speed
and turn rate (from its poses), the target and the onboard tracker's obstacles go in
(`controller.lookahead.beliefs_inputs`), each action's P(safe) comes out, and the policy's
action is kept unless the judge finds it doomed (`contracts.judge_file.judged_actions`, at the
file's threshold). It never
imports torch. Two backends run the same file, as for policies: onnxruntime, and numpy for
boards without an onnxruntime wheel (it reads the weights by the fit's parameter names and runs
`lab.probe.ObstacleSetNetwork`'s arithmetic).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.errors import PolicyFileError
from qnav.contracts.judge_file import (
    CONTEXT_FEATURES,
    CONTEXT_INPUT,
    OBSTACLES_INPUT,
    OUTPUT_NAME,
    JudgeContract,
)
from qnav.contracts.observation import OBSTACLE_SLOT_FEATURES, OBSTACLE_SLOTS
from qnav.controller.onnx_file import float_weights, read_onnx
from qnav.controller.policy import Backend

F32 = NDArray[np.float32]

JudgeLogits = Callable[[F32, F32], F32]
"""A backend: (context, obstacles) inputs -> (N, 3) logits that each action is safe."""

LAYERS = {"per_obstacle": (0, 2, 4), "walls": (0, 2)}
"""The fit's linear layers by parameter name (`lab.probe.ObstacleSetNetwork`: Linear, ReLU,
Linear, ...): the numpy backend applies ReLU between them."""


class DoomJudge:
    """A doom judge file, ready to judge batches of perceived states."""

    def __init__(self, path: Path, backend: Backend = "onnxruntime") -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise PolicyFileError(f"doom judge file {self.path} does not exist")
        contents = read_onnx(self.path)
        self.contract = JudgeContract.from_metadata(contents.metadata, str(path))
        if backend == "numpy":
            self._logits = _numpy_backend(float_weights(contents.initializers), self.path)
        else:
            self._logits = _onnxruntime_backend(self.path)

    def safe_probability(self, context: F32, obstacles: F32) -> NDArray[np.float64]:
        """(N, 3) each action's P(safe) for the inputs `contracts.judge_file.judge_inputs`
        builds."""
        logits = np.asarray(self._logits(context, obstacles), dtype=np.float64)
        return np.asarray(0.5 * (1.0 + np.tanh(logits / 2)))  # the sigmoid, without overflow

    def check_fits(self, dynamics: str, control_period_s: float, driver: str) -> None:
        """Refuse (PolicyFileError) to judge a `driver` (a policy file, a scenario: named in the
        error with its verb) of other dynamics or another control period than the labels'."""
        judge = self.contract
        if (judge.dynamics, judge.control_period_s) != (dynamics, control_period_s):
            raise PolicyFileError(
                f"{self.path} judges {judge.dynamics} dynamics at {judge.control_period_s} s "
                f"({judge.scenario}); {driver} {dynamics} at {control_period_s} s"
            )


def _onnxruntime_backend(path: Path) -> JudgeLogits:
    try:
        import onnxruntime as ort
    except ImportError:  # pragma: no cover - depends on the board
        raise PolicyFileError(
            "onnxruntime is not installed on this machine; use the numpy backend"
        ) from None
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    try:
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as error:  # onnxruntime raises its own exception types
        raise PolicyFileError(f"onnxruntime cannot load {path}: {error}") from None
    found = [i.name for i in session.get_inputs()]
    if found != [CONTEXT_INPUT, OBSTACLES_INPUT]:
        raise PolicyFileError(
            f"{path}: the graph's inputs are {found}; a judge takes "
            f"{[CONTEXT_INPUT, OBSTACLES_INPUT]}"
        )

    def logits(context: F32, obstacles: F32) -> F32:
        feeds = {CONTEXT_INPUT: context, OBSTACLES_INPUT: obstacles}
        return np.asarray(session.run([OUTPUT_NAME], feeds)[0], dtype=np.float32)

    return logits


def _numpy_backend(weights: dict[str, F32], path: Path) -> JudgeLogits:
    try:
        layers = {
            name: [
                (weights[f"{name}.{i}.weight"].T.copy(), weights[f"{name}.{i}.bias"])
                for i in indices
            ]
            for name, indices in LAYERS.items()
        }
    except KeyError as error:
        raise PolicyFileError(f"{path} lacks the judge's weight {error}") from None
    first = layers["per_obstacle"][0][0]
    if first.shape[0] != CONTEXT_FEATURES + OBSTACLE_SLOT_FEATURES:
        raise PolicyFileError(f"{path}: per-obstacle inputs {first.shape[0]} do not fit")

    def mlp(name: str, x: F32) -> F32:
        *hidden, (weight, bias) = layers[name]
        for w, b in hidden:
            x = np.maximum(x @ w + b, 0.0)
        return np.asarray(x @ weight + bias, dtype=np.float32)

    def logits(context: F32, obstacles: F32) -> F32:
        shape = (len(context), OBSTACLE_SLOTS, CONTEXT_FEATURES)
        shared = np.broadcast_to(context[:, None, :], shape)
        doom = np.concatenate(
            [
                mlp("per_obstacle", np.concatenate([shared, obstacles], axis=-1)),
                mlp("walls", context)[:, None],
            ],
            axis=1,
        ).astype(np.float64)
        log_safe = -np.logaddexp(0.0, doom).sum(axis=1)  # log sigmoid(-doom), summed over sources
        # logit(p) = log p - log(1 - p), p = P(no source dooms the action) (the fit's clamp too)
        return np.asarray(log_safe - np.log(-np.minimum(np.expm1(log_safe), -1e-6)), np.float32)

    return logits
