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


def committed_turns(
    greedy: NDArray[np.integer], previous: NDArray[np.integer]
) -> NDArray[np.int64]:
    """The greedy actions (N,), except that a turn against the previous decision's turn keeps
    the previous turn: a turn in place is not reversed before a forward decision (a policy
    file's `turn_commitment`; a learner imitating a planner it cannot see otherwise dithers
    between the two turns where they are close)."""
    left, right = int(Action.LEFT), int(Action.RIGHT)
    reversed_ = ((greedy == left) & (previous == right)) | ((greedy == right) & (previous == left))
    return np.asarray(np.where(reversed_, previous, greedy), dtype=np.int64)


class TurnCommitment:
    """Each stream's previous decision (forward at an episode's start), and `committed_turns`
    against it."""

    def __init__(self, streams: int) -> None:
        self.previous = np.full(streams, int(Action.FORWARD), dtype=np.int64)

    def restart(self, streams: NDArray[np.intp] | slice) -> None:
        """Episodes start in `streams`: nothing to keep turning."""
        self.previous[streams] = int(Action.FORWARD)

    def __call__(self, greedy: NDArray[np.integer]) -> NDArray[np.int64]:
        """The decisions after `greedy` (N,), remembered for the next."""
        self.previous = committed_turns(greedy, self.previous)
        return self.previous.copy()
