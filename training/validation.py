"""Greedy evaluations of a network while it trains, and a layout run's final tests."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from qnav.sim import clutter
from qnav.sim.benchmark import run_benchmark
from qnav.sim.config import LayoutConfig, WorldConfig
from qnav.sim.evaluate import EvalResult, EvalSettings, evaluate
from qnav.sim.layouts import layouts_of
from qnav.training.agent import policy_agent
from qnav.training.config import TrainSettings
from qnav.training.networks import QNetwork

VALIDATION_SEED = 999
"""Layouts of the evaluations during training (the final test uses EvalSettings' own seed)."""


def validation_world(world: WorldConfig, episodes: int) -> WorldConfig:
    """The world of the evaluations during training: in generated layouts, the first `episodes`
    of the validation split, in order (never the training worlds, never BARN's); else `world`."""
    families = world.layout.source.split("+")
    if not world.layout.source or not all(f in clutter.FAMILIES for f in families):
        return world
    layout = replace(world.layout, split="validation", worlds=episodes, order="cycle")
    return replace(world, layout=layout)


def layout_tests(
    world: WorldConfig, network: QNetwork, window: int, worlds: int, turn_commitment: bool = False
) -> dict[str, Any]:
    """A layout run's final tests under BARN's protocol (`sim.benchmark`): the first `worlds`
    of BARN's 300, and as many held-out worlds of BARN's own generator (the cave family's test
    split)."""
    network.eval()
    sets = {
        "barn": LayoutConfig(source="barn", order="cycle", worlds=worlds),
        "held_out": LayoutConfig(source="cave", split="test", worlds=worlds, order="cycle"),
    }
    results = {}
    for name, layout in sets.items():
        tested = replace(world, layout=layout)
        batch = min(64, len(layouts_of(layout) or ()))
        agent = policy_agent(network, tested, batch, window, turn_commitment=turn_commitment)
        results[name] = run_benchmark(tested, agent, "network", num_worlds=batch).summary()
    return results


def evaluate_network(
    world: WorldConfig,
    network: QNetwork,
    window: int,
    *,
    episodes: int,
    seed: int,
    max_steps: int,
    turn_commitment: bool = False,
) -> EvalResult:
    """The network's greedy agent over `episodes` episodes of layouts from `seed`."""
    network.eval()
    settings = EvalSettings(
        episodes=episodes, num_worlds=min(episodes, 100), seed=seed, max_episode_steps=max_steps
    )
    agent = policy_agent(
        network, world, settings.num_worlds, window, turn_commitment=turn_commitment
    )
    return evaluate(world, agent, settings)


class Validation:
    """A run's evaluation during training: its progress.csv columns for the network now."""

    def __init__(self, world: WorldConfig, settings: TrainSettings) -> None:
        self.world = validation_world(world, settings.eval_episodes)
        self.settings = settings

    def __call__(self, network: QNetwork) -> dict[str, float]:
        """Success, collision and unfinished shares on the validation layouts."""
        settings = self.settings
        result = evaluate_network(
            self.world,
            network,
            settings.window,
            episodes=settings.eval_episodes,
            seed=VALIDATION_SEED,
            max_steps=settings.max_episode_steps,
            turn_commitment=settings.imitation.turn_commitment,
        )
        return {
            "eval_success": result.success,
            "eval_collision": result.collision,
            "eval_unfinished": result.unfinished,
        }
