"""The action table's rules."""

from __future__ import annotations

import numpy as np

from qnav.contracts.actions import Action, committed_turns


def test_committed_turns_keep_the_previous_turn_and_nothing_else() -> None:
    forward, left, right = int(Action.FORWARD), int(Action.LEFT), int(Action.RIGHT)
    greedy = np.array([right, left, forward, left, right, forward])
    previous = np.array([left, right, left, left, forward, right])
    assert committed_turns(greedy, previous).tolist() == [left, right, forward, left, right, 0]
