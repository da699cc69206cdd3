"""Greedy evaluations of a network while it trains, and the decisive-state gauge beside them."""

from __future__ import annotations

from qnav.sim.config import WorldConfig
from qnav.sim.decisive import DecisiveStates, GaugeSettings, cached, score
from qnav.sim.evaluate import EvalResult, EvalSettings, evaluate
from qnav.training.agent import greedy_actions, policy_agent
from qnav.training.config import TrainSettings
from qnav.training.networks import QNetwork

VALIDATION_SEED = 999
"""Layouts of the evaluations during training (the final test uses EvalSettings' own seed)."""


def evaluate_network(
    world: WorldConfig,
    network: QNetwork,
    window: int,
    *,
    episodes: int,
    seed: int,
    max_steps: int,
) -> EvalResult:
    """The network's greedy agent over `episodes` episodes of layouts from `seed`."""
    network.eval()
    settings = EvalSettings(
        episodes=episodes, num_worlds=min(episodes, 100), seed=seed, max_episode_steps=max_steps
    )
    return evaluate(world, policy_agent(network, world, settings.num_worlds, window), settings)


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


class Validation:
    """A run's evaluation during training: its progress.csv columns for the network now."""

    def __init__(self, world: WorldConfig, settings: TrainSettings, progress: bool) -> None:
        self.world = world
        self.settings = settings
        self.progress = progress
        self.gauged = bool(settings.gauge_episodes and world.obstacles.count)
        self._decisive: DecisiveStates | None = None  # collected at the first evaluation

    def __call__(self, network: QNetwork) -> dict[str, float]:
        """Success, collision and unfinished shares on the validation layouts, and in obstacle
        worlds the shares of safe and balanced choices on the decisive states."""
        settings = self.settings
        result = evaluate_network(
            self.world,
            network,
            settings.window,
            episodes=settings.eval_episodes,
            seed=VALIDATION_SEED,
            max_steps=settings.max_episode_steps,
        )
        row = {
            "eval_success": result.success,
            "eval_collision": result.collision,
            "eval_unfinished": result.unfinished,
        }
        if self.gauged:
            if self._decisive is None:
                self._decisive = decisive_states(self.world, settings, self.progress)
            judged = score(self._decisive, greedy_actions(network, self._decisive.windows))
            row["decisive_safe"] = round(judged.safe, 4)
            row["decisive_balanced"] = round(judged.balanced, 4)
        return row
