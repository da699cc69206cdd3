"""Imitation before reinforcement: DAgger with the planner given the map as the teacher.

Each round runs `episodes_per_round` episodes in parallel training worlds. At each step the
planner (`sim.mapplan.MapPlanner`) drives with the round's expert share and the network
otherwise, and every state visited is labelled with the planner's action, whoever drove (Ross,
Gordon, Bagnell 2011: the learner is taught in the states its own mistakes lead to). The
network then takes `iterations_per_round` gradient steps of cross-entropy between its outputs
and the labels, on windows drawn uniformly from every round so far, and is validated.

The rounds are stored in the run folder (`imitation/`) like the episodes of reinforcement
learning, so a killed run resumes from its last finished round. The network's outputs stay its
"Q values" for the policy file: the runtime takes their largest, which is the action imitated.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch.nn import functional

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import Outcome
from qnav.sim.config import WorldConfig
from qnav.sim.mapplan import MapPlanner
from qnav.sim.world import Observation, WorldState
from qnav.training.agent import TorchAgent, policy_agent
from qnav.training.collect import collect_round
from qnav.training.config import TrainSettings
from qnav.training.episode_log import Episode, read_rounds, write_round
from qnav.training.networks import QNetwork
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import Progress

_IMITATION_LAYOUT_SEED = 2_000_011
"""Seed of the training layouts' draws in the imitation rounds (the RL rounds use another)."""


class MixedDriver:
    """Each step, the planner's action with probability `share`, else the network's greedy one
    (`sim.evaluate.Agent`)."""

    def __init__(self, learner: TorchAgent, expert: MapPlanner, share: float, seed: int) -> None:
        self.learner = learner
        self.expert = expert
        self.share = share
        self.chance = np.random.default_rng(seed)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.learner.start(worlds, episodes)

    def act(self, observation: Observation) -> NDArray[np.int64]:
        own = self.learner.act(observation)  # always, so the network's window stays current
        if self.share <= 0.0:
            return own
        expert = self.expert.act(observation)
        return np.where(self.chance.random(own.size) < self.share, expert, own)


class Imitation:
    """The imitation phase of one run: its rounds, its dataset and its optimiser."""

    def __init__(
        self,
        world: WorldConfig,
        settings: TrainSettings,
        network: QNetwork,
        optimizer: torch.optim.Optimizer,
        rounds_dir: Path,
    ) -> None:
        if not world.layout.source:
            raise ConfigError("train.imitation.rounds > 0 needs a world of layouts (layout.source)")
        self.world = world
        self.settings = settings
        self.network = network
        self.rounds_dir = rounds_dir
        self.expert = MapPlanner(world)
        self.optimizer = optimizer
        capacity = (
            settings.imitation.rounds
            * settings.imitation.episodes_per_round
            * (world.max_episode_steps + 1)
        )
        self.data = EpisodeReplay(world, capacity, settings.window)
        self.logged = read_rounds(self.rounds_dir)
        for episodes in self.logged:
            for episode in episodes:
                self.data.add(episode)

    def labels(self, state: WorldState) -> NDArray[np.int64]:
        """The planner's action in each world's state (DAgger's label)."""
        assert state.layout is not None
        return self.expert.act_at(state.pose, state.layout)

    def collect(self, round_index: int) -> list[Episode]:
        """The round's episodes (read back if collected before a kill)."""
        if round_index < len(self.logged):
            return self.logged[round_index]
        imitation = self.settings.imitation
        count = imitation.episodes_per_round
        # Greedy, even with imitation.turn_commitment: rounds rolled out committed validated
        # lower (docs/log/barn-learner.md).
        learner = policy_agent(self.network, self.world, count, self.settings.window)
        driver = MixedDriver(
            learner,
            self.expert,
            imitation.share(round_index),
            seed=self.settings.seed * 1_000_003 + round_index,
        )
        ids = np.arange(round_index * count, (round_index + 1) * count, dtype=np.int64)
        self.network.eval()
        episodes = collect_round(
            self.world,
            driver,
            _IMITATION_LAYOUT_SEED + self.settings.seed,
            ids,
            labeller=self.labels,
        )
        write_round(self.rounds_dir, round_index, episodes)
        for episode in episodes:
            self.data.add(episode)
        return episodes

    def learn(self, round_index: int, progress: Progress) -> list[float]:
        """The round's gradient steps; their losses."""
        settings = self.settings
        rng = np.random.default_rng([settings.seed, 7_919, round_index])
        stored = self.data.transitions()
        losses = []
        self.network.train()
        device = next(self.network.parameters()).device
        for _ in range(settings.imitation.iterations_per_round):
            now = stored[rng.integers(0, stored.size, settings.batch_size)]
            windows = self.data.windows(now)
            frames = torch.from_numpy(windows).to(device)
            labels = torch.from_numpy(self.data.action[now]).to(device)
            logits = self.network(frames)
            loss = functional.cross_entropy(logits, labels)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()  # type: ignore[no-untyped-call]
            if settings.grad_clip_norm:
                torch.nn.utils.clip_grad_norm_(self.network.parameters(), settings.grad_clip_norm)
            self.optimizer.step()
            losses.append(float(loss.detach()))
            progress.imitation_iterations += 1
        return losses

    def round(self, round_index: int, progress: Progress) -> dict[str, Any]:
        """Collect and learn one round; its progress.csv row (before validation)."""
        started = time.perf_counter()
        episodes = self.collect(round_index)
        progress.collect_s += time.perf_counter() - started
        started = time.perf_counter()
        losses = self.learn(round_index, progress)
        progress.train_s += time.perf_counter() - started
        progress.imitation_rounds = round_index + 1
        return {
            "phase": "imitation",
            "episodes": (round_index + 1) * self.settings.imitation.episodes_per_round,
            "iterations": progress.imitation_iterations,
            "wall_s": round(progress.collect_s + progress.train_s + progress.eval_s, 2),
            "epsilon": round(self.settings.imitation.share(round_index), 4),
            "train_success": float(np.mean([e.outcome == Outcome.SUCCESS for e in episodes])),
            "train_collision": float(np.mean([e.outcome == Outcome.COLLISION for e in episodes])),
            "loss": float(np.mean(losses)) if losses else float("nan"),
        }
