"""Handlers of `qnav lab`: the research tools of lab/ (calibrate, diagnose, gauge, imitate)."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from typing import TYPE_CHECKING

from qnav.contracts.errors import ConfigError
from qnav.options import config_text, settings_from_args
from qnav.sim.config import WorldConfig, load_world

if TYPE_CHECKING:
    from qnav.lab.imitate import ImitationResult
    from qnav.lab.imitation_settings import ImitationSettings


def calibrate(args: argparse.Namespace) -> int:
    """Random, go-to-target and oracle agents in each paper scenario, beside the paper's rows."""
    from qnav.lab.calibrate import calibrate as measure
    from qnav.lab.calibrate import table
    from qnav.sim import paper
    from qnav.sim.config import scenario

    worlds = {name: scenario(name) for name in paper.RANDOM}
    rows = measure(
        worlds,
        episodes=args.episodes,
        oracle_episodes=args.oracle_episodes,
        seed=args.seed,
        progress=not args.json,
    )
    if args.json:
        print(json.dumps([row.as_dict() for row in rows]))
        return 0
    print(
        f"{args.episodes} episodes of up to 500 steps per scenario for random and go-to-target, "
        f"{args.oracle_episodes} for the oracle (seed {args.seed})\n"
    )
    print(table(rows))
    return 0


def diagnose(args: argparse.Namespace) -> int:
    """Generalisation gap, target sensitivity and action mix of a training run."""
    from qnav.lab.diagnose import diagnose as measure

    print(measure(args.run, fresh_episodes=args.fresh_episodes).render())
    return 0


def gauge(args: argparse.Namespace) -> int:
    """The decisive states of a world with the baselines' scores, or each run's score on its
    own world's states beside its test success."""
    from qnav.contracts.actions import Action
    from qnav.lab.decisive import (
        DRIVERS,
        GaugeResult,
        GaugeSettings,
        cached,
        constant_choice,
        go_to_target_choices,
        perception_ceiling,
        random_expectation,
    )
    from qnav.lab.decisive import score as judge
    from qnav.lab.oracle import PERCEPTION_LEVELS

    rows: list[dict[str, object]] = []
    if not args.runs:
        world = load_world(args.scenario, args.world_config, args.assignments)
        if not world.obstacles.count:
            raise ConfigError(f"scenario {world.name!r} has no moving obstacles: nothing is doomed")
        states = cached(world, GaugeSettings(episodes_per_driver=args.episodes), progress=True)
        if len(states.doomed) == 0:
            raise ConfigError(
                f"no decisive states in {states.visited.sum()} visited: raise --episodes"
            )
        baselines: list[tuple[str, GaugeResult]] = [
            ("random", random_expectation(states)),
            ("go-to-target", judge(states, go_to_target_choices(states))),
            *((f"always {a.name.lower()}", constant_choice(states, a)) for a in Action),
        ]
        if args.ceiling:
            baselines += [
                (f"best choice, {level} state", perception_ceiling(world, states, error))
                for level, error in PERCEPTION_LEVELS.items()
            ]
        for name, result in baselines:
            rows.append(
                {
                    "policy": name,
                    "safe": result.safe,
                    "balanced": result.balanced,
                    **result.by_driver,
                }
            )
        visited = dict(zip(DRIVERS, states.visited.tolist(), strict=True))
        print(
            f"{len(states.doomed)} decisive states in {sum(visited.values())} visited "
            f"(planner {visited['planner']}, go-to-target {visited['go-to-target']})"
        )
    for run in args.runs:
        from qnav.lab.diagnose import decisive_report
        from qnav.lab.gauge import decisive_states
        from qnav.training.run_folder import load_network

        network, settings = load_network(run)
        train = replace(settings.train, gauge_episodes=args.episodes)
        world = replace(settings.world, max_episode_steps=train.max_episode_steps)
        report = decisive_report(
            network, decisive_states(world, train, progress=True), world, train.gamma
        )
        results = run / "results.json"
        test = json.loads(results.read_text())["test"]["success"] if results.exists() else None
        rows.append(
            {
                "policy": str(run),
                "safe": report.safe,
                "balanced": report.balanced,
                **report.by_driver,
                "value_gap": report.value_gap,
                "target_ranks_safe": report.target_ranks_safe,
                "target_gap": report.target_gap,
                "test_success": test,
            }
        )
    for row in rows:
        if args.json:
            print(json.dumps(row))
        else:
            shares = ", ".join(
                f"{key} {value:.3f}" for key, value in row.items() if isinstance(value, float)
            )
            print(f"{row['policy']}: {shares}")
    return 0


def imitate(args: argparse.Namespace) -> int:
    """Copy the oracle planner with the learner's network; test the copy."""
    from qnav.lab.imitate import imitate as measure
    from qnav.lab.imitation_settings import ImitationSettings

    world: WorldConfig = load_world(args.scenario, args.world_config, args.assignments)
    settings = settings_from_args(ImitationSettings(), args)
    if args.print_config:
        print(config_text(settings), end="")
        return 0
    if args.privileged:
        from qnav.lab.privileged import imitate_privileged

        result = imitate_privileged(world, settings)
    else:
        result = measure(world, settings, args.window)
    if args.json:
        print(json.dumps(result.to_dict()))
        return 0
    print(_imitation_report(world.name, settings, result, privileged=args.privileged))
    return 0


def _imitation_report(
    world: str, settings: ImitationSettings, result: ImitationResult, *, privileged: bool
) -> str:
    copy = "a network given the world's state" if privileged else settings.model
    test = result.test
    lines = [
        f"{world}, {copy}: planner success {result.planner_success:.3f} on the "
        f"{settings.episodes} copied episodes ({result.windows} decisions)",
        f"clone agrees with the planner on {result.train_agreement:.1%} of copied decisions, "
        f"{result.held_out_agreement:.1%} of held-out ones",
    ]
    if result.planner_self_agreement is not None:
        lines.append(
            "the planner, asked again on the held-out states, picks the same action on "
            f"{result.planner_self_agreement:.1%} of them"
        )
    lines += [
        f"dodges (the planner's action is not go-to-target's): {result.dodge_share:.1%} of "
        f"held-out decisions; the clone copies {result.dodge_agreement:.1%} of them and goes to "
        f"the target instead on {result.dodge_as_baseline:.1%}",
        f"clone, test protocol ({test.episodes} episodes of up to 500 steps): success "
        f"{test.success:.3f}, collision {test.collision:.3f}, unfinished {test.unfinished:.3f}",
    ]
    lines += [
        f"DAgger round {r['round']}: {r['windows']} decisions, test success {r['test_success']:.3f}"
        for r in result.dagger
    ]
    lines.append(f"{result.minutes} minutes")
    return "\n".join(lines)
