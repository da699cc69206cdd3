"""`qnav eval --barn [DIR]`: BARN's protocol over a folder of worlds (the committed 300 by
default), for a policy or a baseline; and `qnav barn-convert`, which writes the compact file."""

from __future__ import annotations

import argparse
import csv
import json
from dataclasses import asdict, replace
from pathlib import Path

from qnav.contracts.errors import ConfigError
from qnav.sim.benchmark import BenchmarkResult, run_benchmark, top_speed_mps
from qnav.sim.config import WorldConfig, changed_world, scenario
from qnav.sim.evaluate import Agent, GoToTargetAgent, RandomAgent, StreamPolicyAgent
from qnav.sim.layouts import layouts_of
from qnav.verbs.parser import Verbs, verb

BATCH = 64
"""Worlds run together."""
BARN_AGENTS = ("goto", "random", "dwa", "map")
"""The baselines `--agent` runs in BARN's worlds."""


def barn_world(args: argparse.Namespace) -> WorldConfig:
    """The benchmark's world: BARN's robot and protocol, over DIR's worlds (the committed 300
    without DIR), changed by --world-config and --set."""
    source = "barn" if args.barn == "" else str(Path(args.barn))
    world = scenario(args.scenario or "barn")
    world = replace(world, layout=replace(world.layout, source=source, order="cycle"))
    world = changed_world(world, args.world_config, args.assignments)
    if not world.layout.source:
        raise ConfigError("--barn needs a world of layouts: layout.source is empty")
    return world


def barn_agent(args: argparse.Namespace, world: WorldConfig, batch: int) -> tuple[Agent, str]:
    """What drives: the policy (a file or a run folder), else the baseline `--agent`."""
    if args.policy is not None and args.policy.suffix == ".onnx":
        from qnav.controller.policy import Expectation, PolicyRuntime

        expect = Expectation(
            num_beams=world.lidar.num_beams if world.lidar else 0,
            control_period_s=world.control_period_s,
        )
        runtime = PolicyRuntime(args.policy, backend=args.backend, num_streams=batch, expect=expect)
        return StreamPolicyAgent(runtime, batch), f"policy file {args.policy}"
    if args.policy is not None:
        from qnav.training.agent import policy_agent
        from qnav.training.run_folder import load_network

        network, run = load_network(args.policy)
        agent = policy_agent(
            network,
            world,
            batch,
            run.train.window,
            turn_commitment=run.train.imitation.turn_commitment,
        )
        return agent, f"{run.train.model} policy {args.policy}"
    if args.agent == "goto":
        return GoToTargetAgent(), "go-to-target (blind to obstacles)"
    if args.agent == "random":
        return RandomAgent(batch), "random agent"
    if args.agent == "dwa":
        from qnav.sim.dwa import DwaAgent

        return DwaAgent(world, batch), "DWA (lidar only, no map)"
    if args.agent == "map":
        from qnav.sim.mapplan import MapPlanner

        return MapPlanner(world), "planner given the map (an upper bound)"
    raise ConfigError(f"--agent {args.agent} does not run in BARN: choose {', '.join(BARN_AGENTS)}")


def evaluate_barn(args: argparse.Namespace) -> int:
    """Run BARN's protocol once per world and print success, collision, timeout, metric and
    loops, overall and by world (or one JSON object)."""
    if args.lookahead != "off":
        raise ConfigError("--lookahead does not run in BARN's worlds")
    world = barn_world(args)
    layouts = layouts_of(world.layout)
    assert layouts is not None
    batch = min(BATCH, len(layouts))
    agent, label = barn_agent(args, world, batch)
    result = run_benchmark(world, agent, label, num_worlds=batch, progress=not args.json)
    if args.json:
        saved = asdict(result)
        if args.policy is not None and args.policy.is_dir():
            saved["training"] = training_cost(args.policy)
        print(json.dumps(saved))
        return 0
    print(report(result, world))
    return 0


def training_cost(run_dir: Path) -> dict[str, float]:
    """A run's training episodes and minutes (its progress.csv's last round; the final tests'
    time not counted)."""
    with (run_dir / "progress.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows:
        raise ConfigError(f"{run_dir}/progress.csv has no round yet")
    return {"episodes": int(rows[-1]["episodes"]), "minutes": float(rows[-1]["wall_s"]) / 60}


def report(result: BenchmarkResult, world: WorldConfig) -> str:
    """The result as text: the shares and means, then one line per world."""
    speed = top_speed_mps(world)
    lines = [
        f"{result.worlds} ({len(result.runs)} worlds), {result.agent}: one run per world, "
        f"BARN's protocol (100 s, goal within {world.reach_m:g} m, a {world.robot_radius_m:g} m "
        "disc)",
        f"  success    {result.success:.3f}",
        f"  collision  {result.collision:.3f}",
        f"  timeout    {result.timeout:.3f}",
        f"  metric     {result.metric:.3f}  (BARN's, at the robot's top speed {speed:g} m/s)",
        f"  loops      {result.loops:.3f}  (runs that came back to a place they had left)",
        "",
        f"  {'world':>5}  {'outcome':<9} {'time_s':>7} {'metric':>7}  loop",
    ]
    lines += [
        f"  {run.world:>5}  {run.outcome:<9} {run.time_s:>7.1f} {run.metric:>7.3f}  "
        f"{'yes' if run.loop else ''}"
        for run in result.runs
    ]
    return "\n".join(lines)


def convert(args: argparse.Namespace) -> int:
    """Write a BARN-format folder's worlds as one compact file (`sim.barn.convert`)."""
    from qnav.sim.barn import convert as write

    layouts = write(
        args.folder,
        args.out,
        name=args.name or args.folder.name,
        source=args.source,
        commit=args.commit,
        licence=args.licence,
    )
    print(f"wrote {args.out}: {len(layouts)} worlds of up to {layouts.most_cylinders} cylinders")
    return 0


def add_verbs(verbs: Verbs) -> None:
    """`qnav barn-convert`: its options."""
    _add_convert(verbs)


def _add_convert(verbs: Verbs) -> None:
    """`qnav barn-convert FOLDER -o FILE.npz ...`."""
    parser = verb(
        verbs,
        convert,
        "barn-convert",
        help="write a folder of BARN-format worlds as one compact file (sim/data/barn.npz)",
    )
    parser.add_argument("folder", type=Path, help="folder of world_N.world and path_files/")
    parser.add_argument("-o", "--out", type=Path, required=True, help="the .npz to write")
    parser.add_argument("--name", default="", help="the worlds' name in reports (the folder's)")
    parser.add_argument("--source", required=True, help="where the worlds come from (a URL)")
    parser.add_argument("--commit", required=True, help="the source's commit")
    parser.add_argument("--licence", required=True, help="the worlds' licence")
