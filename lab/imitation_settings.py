"""The settings of `qnav lab imitate`, apart from the torch code that uses them, so the verb's
--help (its options are generated from them) imports no torch."""

from __future__ import annotations

from dataclasses import dataclass

from qnav.contracts.settings import check_range
from qnav.training.config import ModelKind


@dataclass(frozen=True)
class ImitationSettings:
    """What `imitate` collects and how it trains the clone."""

    SECTION = "imitate"

    model: ModelKind = "recurrent"
    """Network to train (the paper's sizes)."""
    episodes: int = 2000
    """Planner episodes to copy."""
    held_out_episodes: int = 200
    """Further planner episodes, only to measure the clone's agreement on unseen windows."""
    dagger_rounds: int = 0
    """DAgger rounds after the first copy (Ross et al. 2011): each runs the copy, labels every
    state it visits with the planner's action, adds them to the copied decisions and trains
    `iterations` more steps on all of them (0: none)."""
    dagger_episodes: int = 1000
    """Episodes the copy drives in each DAgger round."""
    test_episodes: int = 200
    """Episodes of the clone's test (the paper's protocol: 200)."""
    iterations: int = 3000
    """Gradient steps."""
    batch_size: int = 256
    """Windows per step."""
    learning_rate: float = 5e-4
    """Adam's learning rate."""
    dodge_weight: float = 1.0
    """Weight of the loss on dodges (decisions where the planner's action is not the go-to-target
    baseline's) against 1 on every other decision."""
    parallel_worlds: int = 32
    """Planner episodes collected at once."""
    max_episode_steps: int = 200
    """Steps before a planner episode is cut (as in training)."""
    seed: int = 0
    """Seed of the layouts, the planner's random sequences, the network and the sampling."""
    threads: int = 2
    """Torch threads."""

    def __post_init__(self) -> None:
        for name in ("episodes", "held_out_episodes", "test_episodes", "iterations"):
            check_range(self, name, getattr(self, name), 1, 10**7)
        check_range(self, "batch_size", self.batch_size, 1, 10**6)
        check_range(self, "parallel_worlds", self.parallel_worlds, 1, 4096)
        check_range(self, "threads", self.threads, 1, 1024)
        check_range(self, "dagger_rounds", self.dagger_rounds, 0, 1000)
        check_range(self, "dagger_episodes", self.dagger_episodes, 1, 10**7)
        check_range(self, "dodge_weight", self.dodge_weight, 1e-3, 1e3)
