"""The decisive-state gauge (`lab.decisive`) beside a training run's evaluations.

`qnav train` hands the run `training_gauge(...)` (`training.validation.Gauge`), so progress.csv's
decisive_ columns show how often the greedy policy avoids a doomed action where it matters; the
training code knows only the protocol, not the oracle planner behind the states.
"""

from __future__ import annotations

from qnav.lab.decisive import DecisiveStates, GaugeSettings, cached, score
from qnav.sim.config import WorldConfig
from qnav.training.agent import greedy_actions
from qnav.training.config import TrainSettings
from qnav.training.networks import QNetwork
from qnav.training.validation import GaugeScore


def decisive_states(
    world: WorldConfig, settings: TrainSettings, progress: bool = False
) -> DecisiveStates:
    """The gauge's decisive states for this world, with the run's window and episode length."""
    gauge = GaugeSettings(
        episodes_per_driver=settings.gauge_episodes,
        max_episode_steps=settings.max_episode_steps,
        window=settings.window,
    )
    return cached(world, gauge, progress)


class DecisiveGauge:
    """The shares of safe and balanced greedy choices on a world's decisive states, collected at
    the first call (not at all in a run that never evaluates)."""

    def __init__(self, world: WorldConfig, settings: TrainSettings, progress: bool) -> None:
        self.world = world
        self.settings = settings
        self.progress = progress
        self._decisive: DecisiveStates | None = None

    def __call__(self, network: QNetwork) -> GaugeScore:
        if self._decisive is None:
            self._decisive = decisive_states(self.world, self.settings, self.progress)
        judged = score(
            self._decisive,
            greedy_actions(network, self._decisive.policy_windows()),
        )
        return GaugeScore(safe=judged.safe, balanced=judged.balanced)


def training_gauge(
    world: WorldConfig, settings: TrainSettings, progress: bool
) -> DecisiveGauge | None:
    """The gauge for a run in `world`, or None where it has nothing to judge: walls-only worlds
    (no decisive states) or `train.gauge_episodes = 0`."""
    if not (settings.gauge_episodes and world.obstacles.count):
        return None
    return DecisiveGauge(world, settings, progress)
