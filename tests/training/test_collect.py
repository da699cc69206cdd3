"""Collection rounds: what is stored."""

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from qnav.sim.config import scenario
from qnav.sim.evaluate import RandomAgent
from qnav.sim.world import WorldState
from qnav.training.collect import collect_round

WORLD = scenario("walls-increment")
IDS = np.arange(4, dtype=np.int64)


def _always(action: int) -> Callable[[WorldState], NDArray[np.int64]]:
    def choose(state: WorldState) -> NDArray[np.int64]:
        return np.full(state.pose.shape[0], action, dtype=np.int64)

    return choose


def test_a_labeller_is_stored_while_the_agent_drives() -> None:
    driven = collect_round(WORLD, RandomAgent(4, seed=1), 0, IDS)
    labelled = collect_round(WORLD, RandomAgent(4, seed=1), 0, IDS, labeller=_always(2))
    for plain, relabelled in zip(driven, labelled, strict=True):
        np.testing.assert_array_equal(relabelled.pose, plain.pose)  # the same drive
        assert (relabelled.action == 2).all() and not (plain.action == 2).all()
