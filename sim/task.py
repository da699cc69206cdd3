"""The navigation task: reward and termination as pure functions of distances.

The learner calls these to recompute reward and termination for a re-drawn target from stored
poses and clearances, without a live environment, so both sides share one definition.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from sim.config import RewardConfig

F64 = NDArray[np.float64]


class Outcome(IntEnum):
    """How a step left the episode."""

    RUNNING = 0
    SUCCESS = 1
    COLLISION = 2


def outcome(distance_to_target_m: F64, clearance_m: F64, robot_radius_m: float) -> NDArray[np.int8]:
    """SUCCESS within l of the target, else COLLISION within l of a surface, else RUNNING.

    Reaching the target is checked first: a robot that touches the target and a wall in the same
    step has reached the target.
    """
    success = distance_to_target_m < robot_radius_m
    collision = ~success & (clearance_m < robot_radius_m)
    return np.where(
        success, Outcome.SUCCESS, np.where(collision, Outcome.COLLISION, Outcome.RUNNING)
    ).astype(np.int8)


def reward(
    distance_to_target_m: F64, clearance_m: F64, robot_radius_m: float, params: RewardConfig
) -> F64:
    """+1 at the target, -1 on collision, else c1*min(0, d_l - 2l) - c2*min(d_g, c3)."""
    result = outcome(distance_to_target_m, clearance_m, robot_radius_m)
    shaping = params.c1 * np.minimum(
        0.0, clearance_m - 2.0 * robot_radius_m
    ) - params.c2 * np.minimum(distance_to_target_m, params.c3_m)
    return np.where(
        result == Outcome.SUCCESS,
        params.success_reward,
        np.where(result == Outcome.COLLISION, params.collision_reward, shaping),
    )
