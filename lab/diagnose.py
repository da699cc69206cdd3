"""Why a run learns or does not: its generalisation gap, and what its greedy policy attends to.

`qnav lab diagnose RUN` prints three measurements that separate the usual failures of a DQN run:

- **Generalisation gap.** The TD error (squared, double-DQN targets from the network itself) on
  transitions from the run's own replay, against the same on fresh episodes collected by the
  same network with the run's own exploration schedule. A fresh error well above the replay's
  means the network memorises its episodes rather than learning the task.
- **Dead lidar channels.** Convolution channels that no probe scan switches on.
- **Target sensitivity.** How much of the LSTM's gate input comes from the target features
  against the lidar features, and whether the greedy action follows the target's bearing on
  fixed scans (the share of probe scans on which it turns towards the target).
- **Action mix** of the greedy policy in the test episodes, with its success, and layout for
  layout against the blind go-to-target controller: how many layouts it completes that the
  blind controller does not, and the reverse (a learner that only seeks the target differs on
  few, and gains nothing on them).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import cast

import numpy as np
import torch
from numpy.typing import NDArray
from torch.nn import functional

from qnav.contracts.actions import NUM_ACTIONS, Action
from qnav.contracts.motion import Outcome
from qnav.contracts.observation import distance_scale_m, encode_frame, encode_scan
from qnav.contracts.policy_file import CONV_CHANNELS
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, episode_outcomes
from qnav.sim.world import Observation, observe, reset
from qnav.training.agent import TorchAgent, policy_agent
from qnav.training.algorithm import bootstrap_windows, double_dqn_target
from qnav.training.collect import collect_round
from qnav.training.episode_log import read_rounds
from qnav.training.networks import QNetwork, channel_activity
from qnav.training.replay import Batch, EpisodeReplay
from qnav.training.run_folder import RunSettings, load_network
from qnav.training.sampling import sample

_FRESH_LAYOUT_SEED = 777_777
"""Layouts of the fresh episodes (neither training, validation nor test use it)."""


@dataclass(frozen=True)
class AgainstBlind:
    """The greedy policy against the blind go-to-target controller on the same test layouts."""

    layouts: int
    """Test layouts both drove."""
    saved: int
    """Layouts the policy completes and the blind controller does not."""
    lost: int
    """Layouts the blind controller completes and the policy does not."""
    blind_success: float
    """The blind controller's success on them."""

    def render(self) -> str:
        """One line for the terminal."""
        same = 1 - (self.saved + self.lost) / self.layouts
        return (
            f"against the blind go-to-target controller ({self.blind_success:.3f}) on the same "
            f"{self.layouts} test layouts: same outcome on {same:.0%}, completes {self.saved} it "
            f"does not, fails {self.lost} it completes"
        )


@dataclass(frozen=True)
class Diagnosis:
    """What `diagnose` measured on one run."""

    replay_td_mse: float
    """Mean squared TD error on transitions sampled from the run's replay."""
    fresh_td_mse: float
    """The same on episodes the network has never trained on."""
    target_gate_std: float
    """Standard deviation of the LSTM gate inputs contributed by the target features."""
    lidar_gate_std: float
    """The same for the lidar features (0 without a lidar or an LSTM)."""
    turns_towards_target: float
    """Share of probes (target to one side) where the greedy action turns towards it."""
    dead_channels: tuple[int, ...]
    """Per convolution layer, the channels positive on none of the probe scans (empty without
    a lidar): a ReLU passes no gradient there, so they never recover."""
    action_mix: tuple[float, float, float]
    """Forward, left and right shares of greedy test actions."""
    test_success: float
    """Success of those test episodes."""
    against_blind: AgainstBlind
    """Those test episodes, layout for layout, against the blind controller's."""

    def render(self) -> str:
        """A few lines for the terminal."""
        gap = self.fresh_td_mse / max(self.replay_td_mse, 1e-12)
        forward, left, right = self.action_mix
        return "\n".join(
            (
                f"TD error (mse): replay {self.replay_td_mse:.4f}, fresh episodes "
                f"{self.fresh_td_mse:.4f} ({gap:.1f}x: above ~1.5x the network memorises)",
                f"LSTM gate input std: target features {self.target_gate_std:.3f}, lidar "
                f"{self.lidar_gate_std:.3f}",
                "greedy action turns towards a target to one side: "
                f"{self.turns_towards_target:.0%}",
                "dead lidar channels per convolution: "
                + (", ".join(f"{d} of {CONV_CHANNELS}" for d in self.dead_channels) or "no lidar"),
                f"greedy test actions: forward {forward:.0%}, left {left:.0%}, right {right:.0%}; "
                f"success {self.test_success:.3f}",
                self.against_blind.render(),
            )
        )


def diagnose(run_dir: Path, fresh_episodes: int = 64, samples: int = 2048) -> Diagnosis:
    """Measure a run (finished or not) on its own replay, fresh episodes and probes."""
    torch.set_num_threads(2)
    network, settings = load_network(run_dir)
    world = replace(settings.world, max_episode_steps=settings.train.max_episode_steps)
    train = settings.train
    capacity = (train.episodes + fresh_episodes) * (train.max_episode_steps + 1)
    replay = EpisodeReplay(world, capacity, train.window)
    for episodes in read_rounds(run_dir / "episodes"):
        for episode in episodes:
            replay.add(episode)
    fresh = EpisodeReplay(world, capacity, train.window)
    agent = policy_agent(network, world, fresh_episodes, train.window, seed=1)
    schedule = np.linspace(0, max(replay.episodes - 1, 0), fresh_episodes).astype(np.int64)
    agent.exploration.epsilon[:] = [train.epsilon(int(i)) for i in schedule]
    for episode in collect_round(world, agent, _FRESH_LAYOUT_SEED, schedule):
        fresh.add(episode)
    rng = np.random.default_rng(0)
    replay_batch, fresh_batch = (
        sample(stored, samples, rng, train.relabel, n_step=train.n_step, gamma=train.gamma)
        for stored in (replay, fresh)
    )
    target_std, lidar_std = _gate_inputs(network, replay_batch)
    actions, success, against_blind = _test_actions(network, settings)
    return Diagnosis(
        replay_td_mse=_td_mse(network, replay_batch, train.window),
        fresh_td_mse=_td_mse(network, fresh_batch, train.window),
        target_gate_std=target_std,
        lidar_gate_std=lidar_std,
        turns_towards_target=_turns_towards_target(network, settings),
        dead_channels=_dead_channels(network, settings),
        action_mix=actions,
        test_success=success,
        against_blind=against_blind,
    )


def _td_mse(network: QNetwork, batch: Batch, window: int) -> float:
    with torch.no_grad():
        features = network.frame_features(torch.from_numpy(batch.frames))
        taken = torch.from_numpy(batch.action).unsqueeze(1)
        q = network.q_from_features(features[:, :window]).gather(1, taken).squeeze(1)
        later = network.q_from_features(
            bootstrap_windows(features, torch.from_numpy(batch.steps), window)
        )
        y = double_dqn_target(
            torch.from_numpy(batch.reward),
            torch.from_numpy(batch.terminal),
            later,
            later,
            torch.from_numpy(batch.discount),
        )
        return float(functional.mse_loss(q, y))


def _gate_inputs(network: QNetwork, batch: Batch) -> tuple[float, float]:
    """Spread of the LSTM's input projection due to the target and to the lidar features."""
    if network.lstm is None:
        return 0.0, 0.0
    with torch.no_grad():
        features = network.frame_features(torch.from_numpy(batch.frames[:, -1:]))[:, 0]
        weight = cast(torch.Tensor, network.lstm.weight_ih_l0)
        split = features.shape[1] - 3
        target = features[:, split:] @ weight[:, split:].T
        lidar = features[:, :split] @ weight[:, :split].T
        return float(target.std()), float(lidar.std()) if split else 0.0


def _turns_towards_target(network: QNetwork, settings: RunSettings, worlds: int = 32) -> float:
    """Over the first scans of `worlds` episodes, with a target 2 m away at 12 bearings to one
    side (30 to 150 degrees left or right), the share of greedy actions that turn that way."""
    world = settings.world
    state = reset(world, np.full(worlds, 3, dtype=np.int64), np.arange(worlds, dtype=np.int64))
    observation: Observation = observe(world, state)
    bearings = np.deg2rad(np.array([30, 60, 90, 120, 150]))
    towards = []
    for side, wanted in ((1.0, Action.LEFT), (-1.0, Action.RIGHT)):
        for bearing in bearings:
            features = np.tile([2.0, side * np.sin(bearing), np.cos(bearing)], (worlds, 1))
            frame = encode_frame(observation.scan_m, features, distance_scale_m(world.lidar))
            window = np.repeat(frame[:, None], settings.train.window, axis=1)
            with torch.no_grad():
                q = network(torch.from_numpy(window)).numpy()
            towards.append(q.argmax(axis=1) == wanted)
    return float(np.mean(towards))


def _dead_channels(network: QNetwork, settings: RunSettings) -> tuple[int, ...]:
    """Per convolution, the channels that no position of the first scans of 256 episodes
    switches on."""
    if network.encoder is None:
        return ()
    scans = torch.from_numpy(first_scans(settings.world, seed=5))
    return tuple(int((layer == 0).sum()) for layer in channel_activity(network.encoder, scans))


def first_scans(world: WorldConfig, seed: int, count: int = 256) -> NDArray[np.float32]:
    """Encoded first scans (count, B) of `count` episodes of the world, layouts from `seed`."""
    state = reset(world, np.full(count, seed, dtype=np.int64), np.arange(count, dtype=np.int64))
    scan = observe(world, state).scan_m
    assert scan is not None
    return encode_scan(scan, distance_scale_m(world.lidar))


class _CountingAgent:
    """A greedy agent that counts the actions it takes."""

    def __init__(self, agent: TorchAgent) -> None:
        self.agent = agent
        self.counts = np.zeros(NUM_ACTIONS, dtype=np.int64)

    def start(self, worlds: np.ndarray, episodes: np.ndarray) -> None:
        self.agent.start(worlds, episodes)

    def act(self, observation: Observation) -> np.ndarray:
        action = self.agent.act(observation)
        self.counts += np.bincount(action, minlength=NUM_ACTIONS)
        return action


def _test_actions(
    network: QNetwork, settings: RunSettings
) -> tuple[tuple[float, float, float], float, AgainstBlind]:
    """The greedy policy on the test protocol's layouts: its action mix, its success, and its
    outcomes against the blind controller's, layout for layout."""
    test = replace(EvalSettings(), num_worlds=50)
    counting = _CountingAgent(policy_agent(network, settings.world, 50, settings.train.window))
    ours = episode_outcomes(settings.world, counting, test)[0] == Outcome.SUCCESS
    blind = episode_outcomes(settings.world, GoToTargetAgent(), test)[0] == Outcome.SUCCESS
    forward, left, right = (counting.counts / max(counting.counts.sum(), 1)).tolist()
    against = AgainstBlind(
        layouts=int(ours.size),
        saved=int((ours & ~blind).sum()),
        lost=int((blind & ~ours).sum()),
        blind_success=float(blind.mean()),
    )
    return (forward, left, right), float(ours.mean()), against
