"""How far the Q-network can perceive doom: a ceiling for learning the decisive moments.

RL hears that an action was doomed only through a collision many steps later, under a re-drawn
target and obstacles. This probe removes all of that: the paper's network is trained by plain
supervision on the planner's per-action doom labels (is each first action doomed, `sim.oracle`)
of windows from planner and go-to-target episodes, then judged on the gauge's held-out decisive
states (`sim.decisive`). If it cannot pick safe actions there, no replay scheme or loss
weighting on top of RL will teach the same network from the same amount of experience: the
limit is perception. `qnav probe` runs it.

The probe is a diagnostic: nothing in training or the product imports it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from contracts.settings import check_range
from sim.config import WorldConfig
from sim.decisive import DecisiveStates, GaugeSettings, cached, is_decisive, score
from training.agent import greedy_actions
from training.networks import QNetwork


@dataclass(frozen=True)
class ProbeSettings:
    """The labelled set and the supervised fit."""

    SECTION = "probe"

    episodes_per_driver: int = 300
    """Episodes driven by each of the planner and go-to-target for the training set."""
    ordinary_share: float = 0.3
    """Share of non-decisive states (all actions safe, or all doomed) kept beside every
    decisive one."""
    seed: int = 778
    """Layout seed of the training set (the gauge's own is 31,337)."""
    epochs: int = 10
    """Passes over the training set."""
    batch_size: int = 128
    """Windows per gradient step."""
    learning_rate: float = 1e-3
    """Adam's learning rate."""
    decisive_weight: float = 3.0
    """Weight of a decisive window's loss against an ordinary one's."""
    scan_difference: bool = False
    """Give the encoder each frame's change since the previous one as a second channel."""
    threads: int = 2
    """Torch threads."""

    def __post_init__(self) -> None:
        check_range(self, "episodes_per_driver", self.episodes_per_driver, 1, 10**7)
        check_range(self, "ordinary_share", self.ordinary_share, 0.0, 1.0)
        check_range(self, "epochs", self.epochs, 1, 10**6)
        check_range(self, "batch_size", self.batch_size, 1, 10**6)
        check_range(self, "learning_rate", self.learning_rate, 0.0, 1.0, exclusive_low=True)
        check_range(self, "decisive_weight", self.decisive_weight, 0.0, 1e6)
        check_range(self, "threads", self.threads, 1, 1024)


class ProbeEpoch(NamedTuple):
    """The fit after one pass over the training set."""

    epoch: int
    """1-based pass."""
    loss: float
    """Mean weighted binary cross-entropy of the pass."""
    train_balanced: float
    """Balanced gauge score on the training set's own decisive states (does it fit?)."""
    safe: float
    """Share of the held-out gauge states where the network's choice is safe."""
    balanced: float
    """The same averaged over doom patterns (1/2 for any choice blind to the scan)."""


def decisive_only(states: DecisiveStates) -> DecisiveStates:
    """The states of a set where some action is doomed and another is not."""
    keep = is_decisive(states.doomed)
    return states._replace(
        windows=states.windows[keep], doomed=states.doomed[keep], driver=states.driver[keep]
    )


def probe(
    world: WorldConfig,
    settings: ProbeSettings = ProbeSettings(),
    gauge: GaugeSettings | None = None,
    progress: bool = False,
) -> list[ProbeEpoch]:
    """Fit the paper's recurrent network to doom labels and judge it on the gauge after each
    pass."""
    gauge = gauge or GaugeSettings()
    torch.set_num_threads(settings.threads)
    labelled = cached(
        world,
        GaugeSettings(
            episodes_per_driver=settings.episodes_per_driver,
            max_episode_steps=gauge.max_episode_steps,
            seed=settings.seed,
            window=gauge.window,
            ordinary_share=settings.ordinary_share,
        ),
        progress,
    )
    held_out = cached(world, gauge, progress)
    fitted = decisive_only(labelled)
    torch.manual_seed(settings.seed)
    network = QNetwork(
        "recurrent",
        world.lidar.num_beams if world.lidar is not None else None,
        scan_difference=settings.scan_difference,
    )
    optimizer = torch.optim.Adam(network.parameters(), lr=settings.learning_rate)
    windows = torch.from_numpy(labelled.windows)
    safe = torch.from_numpy((~labelled.doomed).astype(np.float32))
    weight = torch.from_numpy(
        np.where(is_decisive(labelled.doomed), settings.decisive_weight, 1.0).astype(np.float32)
    )
    order = np.random.default_rng(settings.seed)
    history = []
    for epoch in tqdm(range(1, settings.epochs + 1), desc="probe", disable=not progress):
        network.train()
        total = 0.0
        permutation = order.permutation(len(windows))
        for start in range(0, len(windows), settings.batch_size):
            rows = torch.from_numpy(permutation[start : start + settings.batch_size])
            per_window = torch.nn.functional.binary_cross_entropy_with_logits(
                network(windows[rows]), safe[rows], reduction="none"
            ).mean(dim=1)
            loss = (per_window * weight[rows]).sum() / weight[rows].sum()
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            total += loss.item() * len(rows)
        network.eval()
        judged = score(held_out, greedy_actions(network, held_out.windows))
        fit = score(fitted, greedy_actions(network, fitted.windows))
        history.append(
            ProbeEpoch(epoch, total / len(windows), fit.balanced, judged.safe, judged.balanced)
        )
    return history
