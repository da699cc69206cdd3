"""Handlers of the simulator's verbs: scenarios, settings, eval, render, bench sim."""

from __future__ import annotations

import argparse
import json
import sys

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import IncrementDynamics
from qnav.contracts.settings import to_markdown, to_toml
from qnav.sim.config import SCENARIOS, WorldConfig, load_world, scenario
from qnav.sim.evaluate import RandomAgent


def _world(args: argparse.Namespace) -> WorldConfig:
    return load_world(args.scenario, args.world_config, args.assignments)


def scenarios(args: argparse.Namespace) -> int:
    """Print one line per built-in scenario."""
    print(f"{'scenario':<22} {'dynamics':<10} {'obstacles':>9} {'lidar':>6}")
    for name, config in SCENARIOS.items():
        dynamics = "increment" if isinstance(config.dynamics, IncrementDynamics) else "inertia"
        lidar = str(config.lidar.num_beams) if config.lidar else "none"
        print(f"{name:<22} {dynamics:<10} {config.obstacles.count:>9} {lidar:>6}")
    return 0


def settings(args: argparse.Namespace) -> int:
    """Print the world settings as a commented TOML file (or a Markdown table)."""
    if args.reference:
        sys.stdout.write(settings_reference())
        return 0
    world = _world(args)
    sys.stdout.write(to_markdown(world) if args.markdown else to_toml(world))
    return 0


def settings_reference() -> str:
    """The text of docs/settings.md, generated from the settings classes."""
    increment = to_markdown(scenario("walls-increment")).splitlines()
    dynamics_rows = [row for row in increment[2:] if row.startswith("| `dynamics")]
    return "\n".join(
        [
            "# World settings",
            "",
            "Every setting of the simulator, with its value in the `obstacles-inertia` scenario.",
            "The other scenarios differ only in `name`, `obstacles.count` (0 in the walls-only",
            "scenarios), `dynamics` (below) and `lidar` (none in the `toycar-*` variants).",
            "Print any scenario's settings as a commented TOML file with",
            "`qnav settings --scenario NAME`, edit it and pass it back with `--world-config FILE`,",
            "or change one value with `--set section.field=value`.",
            "",
            "Generated from the settings classes by `make docs`; a test fails when it is stale.",
            "",
            to_markdown(scenario("obstacles-inertia")),
            "Increment dynamics (`walls-increment`, `obstacles-increment`, `toycar-increment`):",
            "",
            *increment[:2],
            *dynamics_rows,
            "",
        ]
    )


def render(args: argparse.Namespace) -> int:
    """Draw one episode to PNG and GIF."""
    from qnav.sim.render import render_episode

    config = _world(args)
    png, gif = render_episode(
        config,
        RandomAgent(1, seed=args.seed),
        args.out,
        seed=args.seed,
        episode=args.episode,
        rays=args.rays,
        max_steps=args.max_steps,
    )
    print(f"wrote {png}\nwrote {gif}")
    return 0


def bench(args: argparse.Namespace) -> int:
    """Simulator throughput on one core."""
    from qnav.sim.bench import format_table, run

    try:
        batches = tuple(int(b) for b in args.batches.split(","))
    except ValueError:
        raise ConfigError(f"--batches {args.batches!r} must be comma-separated integers") from None
    if any(b < 1 for b in batches):
        raise ConfigError(f"--batches {args.batches!r}: every batch size must be at least 1")
    report = run(
        _world(args),
        batches=batches,
        seconds=args.seconds,
        beams=() if args.no_scaling else (90, 180, 360, 720, 1440),
        obstacles=() if args.no_scaling else (0, 1, 5, 10, 20),
    )
    print(json.dumps(report) if args.json else format_table(report))
    return 0
