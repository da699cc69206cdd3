"""The navigation task: reward and termination as pure functions of distances.

The learner calls these to recompute reward and termination for a re-drawn target from stored
poses and clearances, without a live environment, so both sides share one definition.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome, outcome
from qnav.sim.config import RewardConfig

F64 = NDArray[np.float64]


def reward(
    distance_to_target_m: F64,
    clearance_m: F64,
    robot_radius_m: float,
    params: RewardConfig,
    reach_m: float | None = None,
) -> F64:
    """+1 at the target (within `reach_m`, default l), -1 on collision, else
    c1*min(0, d_l - 2l) - c2*min(d_g, c3)."""
    result = outcome(distance_to_target_m, clearance_m, robot_radius_m, reach_m)
    shaping = params.c1 * np.minimum(
        0.0, clearance_m - 2.0 * robot_radius_m
    ) - params.c2 * np.minimum(distance_to_target_m, params.c3_m)
    return np.where(
        result == Outcome.SUCCESS,
        params.success_reward,
        np.where(result == Outcome.COLLISION, params.collision_reward, shaping),
    )
