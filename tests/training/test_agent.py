"""The training side's agent: its greedy choices are the runtime's, turn commitment included."""

from __future__ import annotations

import numpy as np
import torch

from qnav.contracts.actions import Action
from qnav.sim.config import scenario
from qnav.sim.world import observe, reset
from qnav.training.agent import TorchAgent
from qnav.training.config import TrainSettings
from qnav.training.networks import QNetwork, make_network


class _Scripted(torch.nn.Module):
    """Q values that prefer the scripted action of each call, whatever the window."""

    def __init__(self, network: QNetwork, script: list[int]) -> None:
        super().__init__()
        self.frame_size = network.frame_size
        self.anchor = torch.nn.Parameter(torch.zeros(1))
        self.script = script

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        q = torch.zeros(windows.shape[0], 3)
        q[:, self.script.pop(0)] = 1.0
        return q


def test_a_committed_agent_keeps_its_turn_until_it_drives_and_restarts_committed_to_nothing() -> (
    None
):
    world = scenario("cave")
    network = make_network(world, TrainSettings(hidden_size=8))
    left, right, forward = int(Action.LEFT), int(Action.RIGHT), int(Action.FORWARD)
    script = [left, right, right, forward, right, left]
    agents = {
        commit: TorchAgent(
            _Scripted(network, list(script)),  # type: ignore[arg-type]
            1,
            5,
            20.0,
            turn_commitment=commit,
        )
        for commit in (False, True)
    }
    observation = observe(world, reset(world, np.zeros(1, np.int64), np.zeros(1, np.int64)))
    taken: dict[bool, list[int]] = {commit: [] for commit in agents}
    for step in range(len(script)):
        if step == 5:
            for agent in agents.values():
                agent.start(np.arange(1), np.ones(1, np.int64))
        for commit, agent in agents.items():
            taken[commit].append(int(agent.act(observation)[0]))
    assert taken[False] == script
    assert taken[True] == [left, left, left, forward, right, left]
