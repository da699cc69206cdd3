"""Handlers of the simulator's verbs: scenarios, settings, eval, render, bench sim."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict

from contracts.errors import ConfigError
from contracts.settings import to_markdown, to_toml
from sim import paper
from sim.config import SCENARIOS, IncrementDynamics, WorldConfig, load_world, scenario
from sim.evaluate import EvalSettings, RandomAgent
from sim.evaluate import evaluate as run_evaluation


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


def calibrate(args: argparse.Namespace) -> int:
    """The random agent under the test protocol in each paper scenario, beside the paper."""
    rows = {}
    for name in paper.RANDOM:
        settings = EvalSettings(episodes=args.episodes, num_worlds=250, seed=args.seed)
        result = run_evaluation(
            scenario(name), RandomAgent(250, seed=args.seed), settings, progress=not args.json
        )
        rows[name] = {k: v for k, v in asdict(result).items() if k != "mean_steps"}
    if args.json:
        print(json.dumps(rows))
        return 0
    print(
        f"Random agent, {args.episodes} episodes of up to 500 steps per scenario "
        f"(sampling error about +-{(0.25 / args.episodes) ** 0.5:.3f} at most)\n"
    )
    print(
        "| table | scenario | paper success / collision / unfinished "
        "| ours success / collision / unfinished | success difference |"
    )
    print("|---|---|---|---|---|")
    for name, ours in rows.items():
        theirs = paper.RANDOM[name]
        print(
            f"| {paper.TABLES[name]} | {name} "
            f"| {theirs.success:.3f} / {theirs.collision:.3f} / {theirs.unfinished:.3f} "
            f"| {ours['success']:.3f} / {ours['collision']:.3f} / {ours['unfinished']:.3f} "
            f"| {ours['success'] - theirs.success:+.3f} |"
        )
    return 0


def render(args: argparse.Namespace) -> int:
    """Draw one episode to PNG and GIF."""
    from sim.render import render_episode

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
    from sim.bench import format_table, run

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
