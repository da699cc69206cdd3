"""A torch Q-network acting in a batch of worlds: greedy, or epsilon-greedy with held choices."""

from __future__ import annotations

import numpy as np
import torch
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS, TurnCommitment
from qnav.contracts.observation import FrameWindow, distance_scale_m
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import ExplorationHold
from qnav.sim.world import Observation
from qnav.training.networks import QNetwork


def q_values(
    network: QNetwork, windows: NDArray[np.float32], batch: int = 512
) -> NDArray[np.float32]:
    """The network's Q values (K, A) of many windows (K, k, F), a batch at a time."""
    device = next(network.parameters()).device
    parts = [np.zeros((0, NUM_ACTIONS), dtype=np.float32)]
    with torch.no_grad():
        for start in range(0, len(windows), batch):
            chunk = torch.from_numpy(windows[start : start + batch]).to(device)
            parts.append(network(chunk).float().cpu().numpy())
    return np.concatenate(parts)


def greedy_actions(
    network: QNetwork, windows: NDArray[np.float32], batch: int = 512
) -> NDArray[np.int64]:
    """The network's greedy action for each of many windows (K, k, F), a batch at a time."""
    actions: NDArray[np.int64] = q_values(network, windows, batch).argmax(axis=1).astype(np.int64)
    return actions


class TorchAgent:
    """Keeps each world's window of k frames and picks actions from the network's Q values.

    With `epsilon` > 0 a world explores: with probability epsilon it draws a random action and
    holds it for `hold_steps` steps (the paper holds random choices for five steps).
    """

    def __init__(
        self,
        network: QNetwork,
        num_worlds: int,
        window: int,
        max_range_m: float,
        *,
        epsilon: float = 0.0,
        hold_steps: int = 5,
        seed: int = 0,
        turn_commitment: bool = False,
    ) -> None:
        self.network = network
        self.turns = TurnCommitment(num_worlds) if turn_commitment else None
        """Each world's last greedy decision, with `turn_commitment`."""
        self.max_range_m = max_range_m
        self.window = FrameWindow(num_worlds, network.frame_size, window)
        self.exploration = ExplorationHold(num_worlds, epsilon, hold_steps, seed)
        self.last_q = np.zeros((num_worlds, NUM_ACTIONS), dtype=np.float32)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.window.restart(worlds)
        self.exploration.start(worlds)
        if self.turns is not None:
            self.turns.restart(worlds)

    def act(self, observation: Observation) -> NDArray[np.int64]:
        windows = self.window.advance(observation.frames(self.max_range_m))
        with torch.no_grad():
            device = next(self.network.parameters()).device
            q = self.network(torch.from_numpy(windows).to(device)).cpu().numpy()
        self.last_q = q
        action = q.argmax(axis=1)
        if self.turns is not None:
            action = self.turns(action)
        return self.exploration(action)


def policy_agent(
    network: QNetwork,
    world: WorldConfig,
    num_worlds: int,
    window: int,
    *,
    epsilon: float = 0.0,
    hold_steps: int = 5,
    seed: int = 0,
    turn_commitment: bool = False,
) -> TorchAgent:
    """A greedy (or epsilon-greedy) agent of the network for this world, its turns committed
    with `turn_commitment` (`contracts.actions.committed_turns`)."""
    return TorchAgent(
        network,
        num_worlds,
        window,
        distance_scale_m(world.lidar),
        epsilon=epsilon,
        hold_steps=hold_steps,
        seed=seed,
        turn_commitment=turn_commitment,
    )
