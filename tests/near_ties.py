"""Action equality across backends (torch, onnxruntime, numpy), allowing documented near-ties.

Two backends compute the same Q values to within float32 rounding (about 1e-6 here), which
differs between CPU kinds (instruction sets, summation order). Where a step's two best Q values
are closer than that, either action is the network's choice and one CPU's rounding picks it.
So a test over hundreds of steps asks that each action taken scores within `NEAR_TIE_Q` of the
best by the reference's Q values: an exact match but for such near-ties, which a wrong network,
window or state would not pass (their Q values differ by far more).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

NEAR_TIE_Q = 1e-4
"""Largest Q gap (below the reference's best) at which another action counts as a near-tie;
the same bound as the tests' Q-value parity between backends."""


def assert_actions_match_but_near_ties(
    actions: NDArray[np.integer], reference_q: NDArray[np.floating], err_msg: str = ""
) -> int:
    """Assert that each of `actions` (one per row) is the row's argmax of `reference_q` or
    within `NEAR_TIE_Q` of it; the number of near-ties taken the other way."""
    rows = np.arange(len(actions))
    gap = reference_q.max(axis=1) - reference_q[rows, actions]
    assert (gap <= NEAR_TIE_Q).all(), f"{err_msg}: Q gaps {gap[gap > NEAR_TIE_Q]}"
    return int(np.count_nonzero(actions != reference_q.argmax(axis=1)))
