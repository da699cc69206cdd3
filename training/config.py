"""Learner settings, and the two presets: the paper's schedule and our fast one."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

from qnav.contracts.errors import ConfigError
from qnav.contracts.observation import WINDOW_LENGTH
from qnav.contracts.settings import check_range
from qnav.sim.config import WorldConfig

ModelKind = Literal["recurrent", "feedforward"]
"""The Q-network's kind: the paper's LSTM over the window, or feedforward on the last frame."""

Relabel = Literal["paper", "local", "hindsight", "none"]
"""How a sampled transition gets its target (`training.sampling.draw_targets`): a fresh uniform
one in the arena (the paper), a fresh one drawn as the simulator spawns targets around the
robot's pose at that step (local), a position the robot reached later in the same episode
(hindsight), or the episode's own."""


@dataclass(frozen=True)
class ImitationSettings:
    """DAgger (Ross et al. 2011) before the episodes of reinforcement learning: the planner given
    the map (`sim.mapplan`) labels every state the learner visits, and the network learns its
    choices (cross-entropy on its outputs). Worlds of static layouts only."""

    SECTION = "imitation"

    rounds: int = 0
    """DAgger rounds (0: none, the paper's learner alone)."""
    episodes_per_round: int = 64
    """Episodes collected in each round, in parallel worlds."""
    expert_share: float = 1.0
    """Chance that the planner, not the network, takes a step in the first round (DAgger's
    beta); it falls by `expert_share_decay` each round."""
    expert_share_decay: float = 0.5
    """Factor applied to the expert's share after each round."""
    iterations_per_round: int = 400
    """Gradient steps (of `train.batch_size` windows, uniformly from every round so far) after
    each round."""
    turn_commitment: bool = False
    """The network never reverses its previous turn before a forward decision, in the run's
    evaluations and its policy file (`contracts.actions.committed_turns`; the rounds roll it out
    greedy): without it, a network imitating a planner it cannot see dithers on the spot."""

    def __post_init__(self) -> None:
        check_range(self, "rounds", self.rounds, 0, 100_000)
        check_range(self, "episodes_per_round", self.episodes_per_round, 1, 100_000)
        check_range(self, "expert_share", self.expert_share, 0.0, 1.0)
        check_range(self, "expert_share_decay", self.expert_share_decay, 0.0, 1.0)
        check_range(self, "iterations_per_round", self.iterations_per_round, 0, 10**7)

    def share(self, round_index: int) -> float:
        """The expert's share of the steps in a (0-based) round."""
        return float(self.expert_share * self.expert_share_decay**round_index)


@dataclass(frozen=True)
class TrainSettings:
    """Everything that shapes a training run (the world's settings live in sim.config)."""

    SECTION = "train"

    model: ModelKind = "recurrent"
    """Q-network: recurrent (LSTM over the window) or feedforward (last frame only)."""
    seed: int = 0
    """Seed of the network's initial weights, the training layouts and the replay sampling."""
    episodes: int = 600
    """Training episodes (paper: 600)."""
    parallel_worlds: int = 1
    """Episodes collected at once, between training phases (paper: 1)."""
    warmup_episodes: int = 5
    """Episodes collected before the first training iteration (paper: 5)."""
    iterations_per_episode: float = 1000.0
    """Training iterations per collected episode (paper: 1000)."""
    batch_size: int = 256
    """Transitions per training iteration (paper: 256)."""
    learning_rate: float = 1e-4
    """Adam's learning rate (paper: 1e-4)."""
    gamma: float = 0.97
    """Discount factor (paper: 0.97)."""
    n_step: int = 1
    """Rewards summed before bootstrapping, recomputed for each re-drawn target (paper: 1)."""
    target_update_period: int = 10_000
    """Iterations between copies of the online network into the target (paper: 10,000)."""
    target_smoothing: float = 0.0
    """Polyak rate: after every iteration the target moves this fraction towards the online
    network, instead of hard copies every `target_update_period` (0: hard copies, as the paper)."""
    keep_best: bool = False
    """Ship the network of the best validation evaluation rather than the last one."""
    epsilon_start: float = 0.7
    """Exploration probability of the first episode (paper: 0.7)."""
    epsilon_decay: float = 0.98
    """Factor applied to epsilon after each episode (paper: 0.98)."""
    relabel: Relabel = "paper"
    """Target of a sampled transition: fresh random (paper), a later pose (hindsight), own."""
    obstacle_redraw_probability: float = 0.0
    """Chance that a sampled transition sees freshly drawn obstacles along its stored path
    instead of the episode's own (`training.sampling.redraw_obstacles_in_windows`; paper: none)."""
    window: int = WINDOW_LENGTH
    """Observations per network input (paper: k = 5)."""
    hidden_size: int = 512
    """LSTM and hidden layer width (paper: 512)."""
    grad_clip_norm: float = 0.0
    """Clip the gradient's global norm to this (0: no clipping; paper: none)."""
    max_episode_steps: int = 200
    """Steps before a training episode is truncated (paper: 200)."""
    eval_every_episodes: int = 50
    """Episodes between greedy evaluations during training (0: none)."""
    eval_episodes: int = 100
    """Episodes of each greedy evaluation during training (episodes as long as in training)."""
    snapshot_every_episodes: int = 0
    """Save the online network every this many episodes, for the action-map figure (0: never)."""
    final_eval_episodes: int = 200
    """Episodes of the final test (paper: 200)."""
    threads: int = 2
    """Torch threads."""
    device: str = "auto"
    """Torch device for learning: "cpu", "cuda", or "auto" (cuda when available)."""
    bf16_matmul: bool = False
    """Run the training forward passes under bfloat16 autocast (about 1.7x faster where the CPU
    has AMX or AVX-512 BF16, ignored where it has neither); weights and loss stay float32."""
    imitation: ImitationSettings = field(default_factory=ImitationSettings)
    """Imitation of the planner given the map before the episodes (none in the paper)."""

    def __post_init__(self) -> None:
        check_range(self, "episodes", self.episodes, 0, 10_000_000)
        check_range(self, "parallel_worlds", self.parallel_worlds, 1, 4096)
        check_range(self, "warmup_episodes", self.warmup_episodes, 0, self.episodes)
        check_range(self, "iterations_per_episode", self.iterations_per_episode, 0.0, 1e6)
        check_range(self, "batch_size", self.batch_size, 1, 1_000_000)
        check_range(self, "learning_rate", self.learning_rate, 0.0, 1.0, exclusive_low=True)
        check_range(self, "gamma", self.gamma, 0.0, 1.0)
        check_range(self, "n_step", self.n_step, 1, 1000)
        check_range(self, "target_update_period", self.target_update_period, 1, 10**9)
        check_range(self, "target_smoothing", self.target_smoothing, 0.0, 1.0)
        check_range(self, "epsilon_start", self.epsilon_start, 0.0, 1.0)
        check_range(self, "epsilon_decay", self.epsilon_decay, 0.0, 1.0)
        check_range(self, "obstacle_redraw_probability", self.obstacle_redraw_probability, 0.0, 1.0)
        check_range(self, "window", self.window, 1, 1000)
        check_range(self, "hidden_size", self.hidden_size, 1, 100_000)
        check_range(self, "grad_clip_norm", self.grad_clip_norm, 0.0, 1e9)
        check_range(self, "max_episode_steps", self.max_episode_steps, 1, 10**7)
        check_range(self, "eval_every_episodes", self.eval_every_episodes, 0, 10**7)
        check_range(self, "eval_episodes", self.eval_episodes, 1, 10**7)
        check_range(self, "snapshot_every_episodes", self.snapshot_every_episodes, 0, 10**7)
        check_range(self, "final_eval_episodes", self.final_eval_episodes, 1, 10**7)
        check_range(self, "threads", self.threads, 1, 1024)
        if self.device not in ("auto", "cpu", "cuda") and not self.device.startswith("cuda:"):
            raise ConfigError(f"train.device = {self.device!r}: choose auto, cpu, cuda or cuda:N")

    def epsilon(self, episode: int) -> float:
        """Exploration probability of the given (0-based) training episode."""
        return self.epsilon_start * self.epsilon_decay**episode


PAPER = TrainSettings()
"""The paper's schedule exactly: 1000 iterations of batch 256 after each of 600 episodes."""

FAST = replace(
    PAPER,
    n_step=5,
    parallel_worlds=8,
    iterations_per_episode=8.0,
    learning_rate=5e-4,
    target_smoothing=0.005,
    grad_clip_norm=10.0,
    bf16_matmul=True,
    keep_best=True,
    obstacle_redraw_probability=1.0,
)
"""Our schedule for two CPU cores: the paper's budget of episodes at most, far fewer iterations,
five-step returns, and fresh obstacles for every sampled transition (no effect without
obstacles)."""

FAST_EPISODES_WITHOUT_OBSTACLES = 250
"""The fast preset's episodes in walls-only worlds, which it learns within 200."""

DAGGER = replace(
    FAST,
    episodes=0,
    warmup_episodes=0,
    # 64 validation worlds picked the second round's network of a run (0.80 on them, 0.70 on
    # 256) over its last (0.77 on 256): the shipped network is chosen on 256.
    eval_episodes=256,
    final_eval_episodes=300,
    imitation=ImitationSettings(
        rounds=10, episodes_per_round=64, iterations_per_round=800, turn_commitment=True
    ),
)
"""Imitation of the planner given the map (DAgger), no reinforcement learning after it: for
worlds of static layouts (the cave and clutter scenarios; docs/barn.md's runs)."""

PRESETS = {"paper": PAPER, "fast": FAST, "dagger": DAGGER}


def preset(name: str, world: WorldConfig) -> TrainSettings:
    """A named preset for a world: the fast one trains walls-only worlds for 250 episodes."""
    try:
        settings = PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}: choose one of {', '.join(PRESETS)}") from None
    if name == "fast" and world.obstacles.count == 0:
        settings = replace(settings, episodes=FAST_EPISODES_WITHOUT_OBSTACLES)
    if world.layout.source:  # BARN's time limit: a cluttered world takes longer to cross
        settings = replace(settings, max_episode_steps=world.max_episode_steps)
    return settings
