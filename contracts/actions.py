"""The discrete action table of the paper: move forward, turn left, turn right."""

from __future__ import annotations

from enum import IntEnum

import numpy as np
from numpy.typing import NDArray


class Action(IntEnum):
    """Index of each action in the Q-network's output."""

    FORWARD = 0
    LEFT = 1
    RIGHT = 2


NUM_ACTIONS = len(Action)


def forward_command(action: NDArray[np.integer]) -> NDArray[np.float64]:
    """1.0 where the action drives forward, else 0.0."""
    return np.asarray(action == Action.FORWARD, dtype=np.float64)


def turn_command(action: NDArray[np.integer]) -> NDArray[np.float64]:
    """+1.0 for a left (counter-clockwise) turn, -1.0 for a right turn, else 0.0."""
    left = np.asarray(action == Action.LEFT, dtype=np.float64)
    return left - np.asarray(action == Action.RIGHT, dtype=np.float64)
