"""Handlers of the simulator's verbs: scenarios, eval, render."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, cast

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import IncrementDynamics
from qnav.contracts.settings import to_markdown
from qnav.options import add_print_config, config_text, settings_from_args
from qnav.sim.config import SCENARIOS, WorldConfig, changed_world, load_world, scenario
from qnav.sim.evaluate import (
    Agent,
    EvalResult,
    EvalSettings,
    GoToTargetAgent,
    RandomAgent,
    StreamPolicyAgent,
)
from qnav.sim.evaluate import evaluate as run_evaluation
from qnav.verbs.parser import Verbs, flag, lookahead_option, settings_options, verb, world_options

if TYPE_CHECKING:
    from qnav.tracking import LookaheadAgent


def _world(args: argparse.Namespace) -> WorldConfig:
    return load_world(args.scenario, args.world_config, args.assignments)


def scenarios(args: argparse.Namespace) -> int:
    """Print one line per built-in scenario, or (--reference) every world setting."""
    if args.reference:
        sys.stdout.write(settings_reference())
        return 0
    print(f"{'scenario':<22} {'dynamics':<10} {'obstacles':>9} {'lidar':>6}")
    for name, config in SCENARIOS.items():
        dynamics = "increment" if isinstance(config.dynamics, IncrementDynamics) else "inertia"
        lidar = str(config.lidar.num_beams) if config.lidar else "none"
        print(f"{name:<22} {dynamics:<10} {config.obstacles.count:>9} {lidar:>6}")
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
            "`qnav eval --scenario NAME --print-config`, edit it and pass it back with",
            "`--world-config FILE`, or change one value with `--set section.field=value`.",
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


def evaluate(args: argparse.Namespace) -> int:
    """The paper's test protocol with the random agent or a trained policy (BARN's with
    --barn)."""
    if args.barn is not None:
        from qnav.verbs.barn import evaluate_barn

        return evaluate_barn(args)
    eval_settings = settings_from_args(EvalSettings(), args)
    worlds = min(eval_settings.num_worlds, eval_settings.episodes)
    world, agent, label = _evaluated(args, worlds, eval_settings.seed)
    if args.print_config:
        print(config_text(world, markdown=args.markdown), end="")
        return 0
    _check_views(args)
    shield = None
    if args.lookahead != "off":
        shield = agent = _looking_ahead(args, agent, world, worlds, eval_settings.seed)
        label += f", the controller's look ahead in {args.lookahead} mode and proximity stop"
    if args.random_action_prob:
        label += f" with {args.random_action_prob:.0%} random actions"
    if args.policy is None and args.agent == "oracle":
        result, planning = _planned(args, world, eval_settings)
        label += planning
    else:
        result = run_evaluation(world, agent, eval_settings, progress=not args.json)
    if args.json:
        print(json.dumps(result.fractions()))
        return 0
    steps = eval_settings.max_episode_steps
    print(f"{world.name}, {label}, {result.episodes} episodes of up to {steps} steps")
    for name in ("success", "collision", "unfinished"):
        value = getattr(result, name)
        print(f"  {name:<11} {value:.3f} +- {result.standard_error(value):.3f}")
    print(f"  mean length {result.mean_steps:.1f} steps")
    if shield is not None:
        print(f"  overruled  {shield.overruled_share:.3f} of the policy's decisions")
    return 0


def _evaluated(args: argparse.Namespace, worlds: int, seed: int) -> tuple[WorldConfig, Agent, str]:
    """The world, the agent that acts in it and what to call it: a policy file's, a run's
    network's, or (without --policy) random, go-to-target or the planner's (run apart)."""
    if args.policy is not None and args.policy.suffix == ".onnx":
        return _file_agent(args, worlds, seed)
    if args.policy is not None:
        return _run_agent(args, worlds, seed)
    world = load_world(args.scenario or "walls-inertia", args.world_config, args.assignments)
    if args.agent == "goto":
        return world, GoToTargetAgent(), "go-to-target baseline"
    if args.agent == "random":
        return world, RandomAgent(worlds, seed=seed), "random agent"
    return world, RandomAgent(worlds, seed=seed), "oracle planner (knows the future)"


def _file_agent(args: argparse.Namespace, worlds: int, seed: int) -> tuple[WorldConfig, Agent, str]:
    """A policy file through the onboard runtime, in its own scenario unless --scenario."""
    from qnav.controller.policy import Expectation, PolicyRuntime

    probe = PolicyRuntime(args.policy, backend=args.backend)
    world = load_world(
        args.scenario or probe.contract.scenario, args.world_config, args.assignments
    )
    expect = Expectation(
        num_beams=world.lidar.num_beams if world.lidar else 0,
        control_period_s=world.control_period_s,
    )
    runtime = PolicyRuntime(args.policy, backend=args.backend, num_streams=worlds, expect=expect)
    agent = StreamPolicyAgent(runtime, worlds, args.random_action_prob, seed=seed)
    return world, agent, f"policy file {args.policy} ({args.backend})"


def _run_agent(args: argparse.Namespace, worlds: int, seed: int) -> tuple[WorldConfig, Agent, str]:
    """A training run's network (torch), in the run's world unless --scenario."""
    from qnav.training.agent import policy_agent
    from qnav.training.run_folder import load_network

    network, run = load_network(args.policy)
    world = (
        load_world(args.scenario, args.world_config, args.assignments)
        if args.scenario
        else changed_world(run.world, args.world_config, args.assignments)
    )
    agent = policy_agent(
        network,
        world,
        worlds,
        run.train.window,
        epsilon=args.random_action_prob,
        hold_steps=1,
        seed=seed,
        turn_commitment=run.train.imitation.turn_commitment,
    )
    return world, agent, f"{run.train.model} policy {args.policy}"


def _check_views(args: argparse.Namespace) -> None:
    """ConfigError naming the options that do not go together: the planner's views of the
    state, the look ahead beside anything but a greedy policy, the tracker's range noise."""
    planner = args.policy is None and args.agent == "oracle"
    if args.state_error and not planner:
        raise ConfigError("--state-error is for --agent oracle (the planner's view of the state)")
    looking = args.lookahead != "off"
    goto = args.policy is None and args.agent == "goto"
    if looking and ((args.policy is None and not goto) or args.random_action_prob):
        raise ConfigError(
            "--lookahead runs beside a greedy policy: give --policy (or --agent goto), "
            "no random actions"
        )
    if args.range_noise_m and not looking:
        raise ConfigError("--range-noise-m is the noise the tracker reads: give --lookahead")
    if args.range_noise_m < 0:
        raise ConfigError(
            f"--range-noise-m = {args.range_noise_m} is out of range: allowed [0, inf)"
        )


def _looking_ahead(
    args: argparse.Namespace, agent: Agent, world: WorldConfig, worlds: int, seed: int
) -> LookaheadAgent:
    """The policy's agent with the controller's look ahead in --lookahead's mode and the
    proximity stop below it, as the shipped controller runs them; go-to-target's choice as a
    policy's (`tracking.GoToTargetValues`)."""
    from qnav.controller.perception import TrackerSettings
    from qnav.tracking import (
        GoToTargetValues,
        LookaheadAgent,
        QAgent,
        fitted_proximity,
        lookahead_settings,
    )

    inner = GoToTargetValues(worlds) if isinstance(agent, GoToTargetAgent) else agent
    return LookaheadAgent(
        cast(QAgent, inner),  # a StreamPolicyAgent, a TorchAgent or go-to-target's values
        world,
        worlds,
        tracker=TrackerSettings(),
        lookahead=lookahead_settings(args.lookahead),
        range_noise_m=args.range_noise_m,
        seed=seed,
        proximity=fitted_proximity(world),
    )


def _planned(
    args: argparse.Namespace, world: WorldConfig, eval_settings: EvalSettings
) -> tuple[EvalResult, str]:
    """The oracle planner's episodes, on the truth or a noisy estimate (--state-error), and
    what the label adds (on the onboard tracker's estimate: a policy with --lookahead plan)."""
    from qnav.lab.oracle import PERCEPTION_LEVELS, run_oracle

    error = PERCEPTION_LEVELS[args.state_error] if args.state_error else None
    result = run_oracle(world, eval_settings, state_error=error, progress=not args.json)
    if error is None:
        return result, ""
    return result, f", planning on a {args.state_error} estimate of the state"


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


def add_verbs(verbs: Verbs) -> None:
    """`qnav scenarios`, `qnav eval` and `qnav render`: their options."""
    _add_scenarios(verbs)
    _add_eval(verbs)
    _add_render(verbs)


def _add_scenarios(verbs: Verbs) -> None:
    """`qnav scenarios [--reference]`."""
    parser = verb(verbs, scenarios, "scenarios", help="list the built-in scenarios")
    flag(
        parser,
        "--reference",
        "print the reference of every world setting instead (docs/settings.md)",
    )


def _add_eval(verbs: Verbs) -> None:
    """`qnav eval`: the test protocol over an agent, a run or a policy file."""
    parser = verb(
        verbs,
        evaluate,
        "eval",
        help="run the paper's test protocol and print success, collision, unfinished",
    )
    world_options(parser, default=None)
    parser.add_argument(
        "--agent",
        default="random",
        choices=["random", "goto", "oracle", "dwa", "map"],
        help="without --policy: random (the paper's Random rows), goto (turn to the target "
        "and drive, blind to obstacles), oracle (a planner that knows the obstacles' future: "
        "an upper bound on success; slow); with --barn also dwa (the Dynamic Window Approach "
        "on the lidar, no map) and map (a planner given the map: an upper bound)",
    )
    parser.add_argument(
        "--barn",
        nargs="?",
        const="",
        metavar="DIR",
        help="BARN's protocol, one run per world, over DIR's world_N.world files (with "
        "path_files/ beside them, as published), or BARN's 300 worlds (committed) without DIR: "
        "success, collision, timeout, BARN's metric and loops, overall and by world",
    )
    parser.add_argument(
        "--state-error",
        choices=["exact", "lidar-grade", "tracker", "coarse"],
        help="with --agent oracle: plan on a noisy estimate of the state, as a perceive-then-plan "
        "controller would (errors in lab.oracle.PERCEPTION_LEVELS)",
    )
    lookahead_option(parser, "with --policy or --agent goto: ")
    parser.add_argument(
        "--range-noise-m",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="with --lookahead: Gaussian noise added to the ranges the tracker reads",
    )
    parser.add_argument(
        "--policy",
        type=Path,
        metavar="RUN_DIR|FILE.onnx",
        help="a training run folder (torch) or an exported policy file (the onboard runtime); "
        "without it the random agent acts",
    )
    parser.add_argument(
        "--backend",
        default="onnxruntime",
        choices=["onnxruntime", "numpy"],
        help="runtime backend for a policy file (default onnxruntime)",
    )
    parser.add_argument(
        "--random-action-prob",
        type=float,
        default=0.0,
        metavar="P",
        help="with --policy: take a random action with probability P at each step",
    )
    add_print_config(parser, markdown=True)
    settings_options(parser, "qnav.sim.evaluate:EvalSettings", "test protocol")
    flag(parser, "--json", "print one JSON object")


def _add_render(verbs: Verbs) -> None:
    """`qnav render`: one episode drawn."""
    parser = verb(verbs, render, "render", help="draw an episode to PNG and animated GIF")
    world_options(parser, "obstacles-inertia")
    parser.add_argument("--agent", default="random", choices=["random"], help="who acts")
    parser.add_argument("--seed", type=int, default=0, help="world seed (default 0)")
    parser.add_argument("--episode", type=int, default=0, help="episode index of that seed")
    parser.add_argument("--max-steps", type=int, default=None, help="cut the episode short")
    flag(parser, "--rays", "draw the lidar rays")
    parser.add_argument("--out", type=Path, default=Path("out/render"), help="output folder")
