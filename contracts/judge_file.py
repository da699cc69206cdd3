"""The doom judge file's contract: a learned judgement of which actions are doomed.

A doom judge (`qnav lab label FOLDER ... --export FILE`, docs/learner.md) is a network fitted to
the simulator planner's labels of whether each first action is doomed (every continuation
collides within the labels' horizon). The controller asks it at every decision, from what the
car perceives (its own speed and turn rate from its poses, the target, the onboard tracker's
obstacles), and keeps the policy's action unless the judge finds it doomed
(`judged_actions`, the rule the file's threshold was chosen for).

The graph takes two inputs built by `judge_inputs` and returns the logit that each action of
`contracts.actions.Action` is safe; the metadata holds a `JudgeContract` (`qnav.`-prefixed JSON
entries, as a policy file's).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.errors import PolicyFileError
from qnav.contracts.observation import (
    OBSTACLE_FEATURES,
    OBSTACLE_SLOT_FEATURES,
    OBSTACLE_SLOTS,
    TARGET_FEATURES,
    encode_target,
    obstacle_features,
    target_features,
)
from qnav.contracts.policy_file import METADATA_PREFIX, metadata_values

JUDGE_FORMAT = "qnav-judge/1"
"""Value of the `qnav.format` metadata key of a doom judge file."""

CONTEXT_INPUT = "context"
"""The graph's first input: (batch, CONTEXT_FEATURES) float32, the robot's forward speed (m/s)
and turn rate (rad/s), then the encoded target (`contracts.observation.encode_target`)."""

CONTEXT_FEATURES = 2 + TARGET_FEATURES
"""Values of the context input."""

OBSTACLES_INPUT = "obstacles"
"""The graph's second input: (batch, OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES) float32, the
nearest obstacles as `contracts.observation.obstacle_features` encodes them, one slot per row."""

OUTPUT_NAME = "safe_logits"
"""The graph's output: (batch, 3) float32, the logit that each action is safe, by `Action`."""


@dataclass(frozen=True)
class JudgeContract:
    """Everything the controller needs to feed a doom judge file and act on its answer."""

    scenario: str
    """Name of the world whose planner labelled the states."""
    dynamics: str
    """Dynamics model of that world (inertia or increment): a policy of another is refused."""
    control_period_s: float
    """Time between decisions the labels assumed: a policy of another period is refused."""
    max_range_m: float
    """Length the target distance is divided by in the context input."""
    threshold: float
    """The policy's action is kept where the judge's P(safe) exceeds this (chosen on validation
    layouts, `judged_actions`)."""
    horizon_s: float
    """An action is doomed when every continuation collides within this many seconds."""
    training: Mapping[str, Any]
    """Where the labels came from: the label folder, its rounds and labelled states, and the
    training run whose stored steps they were drawn at (where one was)."""
    evaluation: Mapping[str, float]
    """Go-to-target shielded by this judge on the test protocol at `threshold`: success from
    the world's truth, from the onboard tracker's estimate and with noisy scans, and episodes."""
    commit: str
    """Source revision the judge was exported with."""
    obstacle_slots: int = OBSTACLE_SLOTS
    """Obstacle slots of the second input."""
    slot_features: int = OBSTACLE_SLOT_FEATURES
    """Values per slot."""
    format: str = JUDGE_FORMAT
    """File layout version."""

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold < 1.0:
            raise PolicyFileError(f"threshold = {self.threshold} is not a probability in (0, 1)")
        if (self.obstacle_slots, self.slot_features) != (OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES):
            raise PolicyFileError(
                f"the judge reads {self.obstacle_slots} obstacle slots of {self.slot_features} "
                f"values; this runtime encodes {OBSTACLE_SLOTS} of {OBSTACLE_SLOT_FEATURES}"
            )

    def to_metadata(self) -> dict[str, str]:
        """ONNX metadata entries: one `qnav.<field>` key per field, each value JSON."""
        return {METADATA_PREFIX + name: json.dumps(value) for name, value in asdict(self).items()}

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str], source: str) -> JudgeContract:
        """Read the contract back; `source` names the file in errors."""
        found = metadata.get(METADATA_PREFIX + "format")
        if found != json.dumps(JUDGE_FORMAT):
            raise PolicyFileError(
                f"{source} is not a qnav doom judge (format {found}; expected {JUDGE_FORMAT!r}): "
                "export one with `qnav lab label FOLDER ... --export FILE`"
            )
        values = metadata_values(cls, metadata, source)
        try:
            return cls(**values)
        except TypeError as error:
            raise PolicyFileError(f"{source}: malformed metadata: {error}") from None


def encoded_surroundings(
    pose: NDArray[np.floating],
    target_xy: NDArray[np.floating],
    obstacle_xy: NDArray[np.floating],
    obstacle_velocity: NDArray[np.floating],
    max_range_m: float,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The encoded target (K, TARGET_FEATURES) and obstacles (K, OBSTACLE_FEATURES) of K worlds
    known in the room's frame (a car's belief, or a simulated world's truth): poses (K, 3),
    targets (K, 2), obstacles (K, M, 2) and their velocities (K, M, 2)."""
    return (
        encode_target(target_features(pose, target_xy), max_range_m),
        obstacle_features(pose, obstacle_xy, obstacle_velocity),
    )


def judge_inputs(
    velocity: NDArray[np.floating],
    encoded_target: NDArray[np.floating],
    obstacles: NDArray[np.floating],
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The judge's (context, obstacles) inputs from the robot's velocities (K, 2: forward speed,
    turn rate), encoded targets (K, 3) and encoded obstacles (K, OBSTACLE_FEATURES)."""
    context = np.concatenate([velocity, encoded_target], axis=1).astype(np.float32)
    if obstacles.shape[1:] != (OBSTACLE_FEATURES,):
        raise ValueError(f"obstacles of shape {obstacles.shape}: expected (K, {OBSTACLE_FEATURES})")
    slots = obstacles.reshape(len(context), OBSTACLE_SLOTS, OBSTACLE_SLOT_FEATURES)
    return context, np.ascontiguousarray(slots, dtype=np.float32)


def judged_actions(
    preferred: NDArray[np.integer],
    safe_probability: NDArray[np.floating],
    threshold: float,
) -> NDArray[np.int64]:
    """(N,) each preferred action (N,) where the judge's P(safe) (N, A) exceeds `threshold`,
    else the action it judges safest. A miss (keeping a doomed action) ends the episode while a
    false alarm costs a detour, so a good judge's best threshold lies above 1/2."""
    if safe_probability.shape[1:] != (NUM_ACTIONS,):
        raise ValueError(f"safe_probability of shape {safe_probability.shape}: expected (N, 3)")
    rows = np.arange(len(preferred))
    keep = safe_probability[rows, preferred] > threshold
    return np.where(keep, preferred, safe_probability.argmax(axis=1)).astype(np.int64)
