"""Handlers of `qnav bench`: simulator, learner, policy, look ahead, controller, cluster, bridge."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from qnav.contracts.errors import ConfigError
from qnav.contracts.policy_file import WEIGHT_TYPES
from qnav.sim.config import WorldConfig, load_world
from qnav.verbs.parser import Verbs, flag, lookahead_option, verb, world_options

if TYPE_CHECKING:
    from qnav.controller.bench_e2e import Drive


def bench_sim(args: argparse.Namespace) -> int:
    """Simulator throughput on one core."""
    from qnav.sim.bench import format_table, run

    try:
        batches = tuple(int(b) for b in args.batches.split(","))
    except ValueError:
        raise ConfigError(f"--batches {args.batches!r} must be comma-separated integers") from None
    if any(b < 1 for b in batches):
        raise ConfigError(f"--batches {args.batches!r}: every batch size must be at least 1")
    world = load_world("barn" if args.barn else args.scenario, args.world_config, args.assignments)
    if args.barn:  # every world of the batch in a layout of its own
        world = replace(world, layout=replace(world.layout, order="random"))
    report = run(
        world,
        batches=batches,
        seconds=args.seconds,
        beams=() if args.no_scaling else (90, 180, 360, 720, 1440),
        obstacles=() if args.no_scaling else (0, 1, 5, 10, 20),
    )
    print(json.dumps(report) if args.json else format_table(report))
    return 0


def bench_learner(args: argparse.Namespace) -> int:
    """Training iteration cost against the machine's own matrix-product rate."""
    from qnav.training.bench import format_report, run

    report = run(
        model=args.model, batch_size=args.batch, repeats=args.repeats, threads=args.threads
    )
    print(json.dumps(report) if args.json else format_report(report))
    return 0


def bench_lookahead(args: argparse.Namespace) -> int:
    """Per-decision wall time of the controller's look ahead."""
    from qnav.tracking import time_lookahead

    world = load_world(args.scenario, args.world_config, args.assignments)
    if args.cars < 1:
        raise ConfigError(f"--cars = {args.cars}: drive at least one car")
    report = time_lookahead(world, args.decisions, worlds=args.cars)
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"{world.name}, {report['decisions']:.0f} decisions, one car at a time (ms):")
    for name in ("track", "shield", "plan"):
        print(
            f"  {name:<7} p50 {report[name + '_ms_p50']:6.1f}  p99 {report[name + '_ms_p99']:6.1f}"
        )
    print(
        f"the shield's forecast of all {args.cars} cars at once, per car (ms): p50 "
        f"{report['shield_batched_ms_p50']:.2f}  p99 {report['shield_batched_ms_p99']:.2f}"
    )
    return 0


def bench_policy(args: argparse.Namespace) -> int:
    """Per-decision latency of each runtime backend."""
    import tempfile

    from qnav.controller.bench import format_report, run

    with tempfile.TemporaryDirectory() as scratch:
        policy = args.policy or _paper_sized_policy(Path(scratch), args.weights)
        report = run(policy, args.backends.split(","), args.decisions, args.gap_ms / 1e3)
        if args.policy is None:
            report["policy"] = f"{PAPER_SIZED}, {args.weights} weights"
    print(json.dumps(report) if args.json else format_report(report))
    return 0


PAPER_SIZED = "untrained paper-sized recurrent (720 beams, LSTM 512, k = 5)"


def _paper_sized_policy(folder: Path, weight_type: str = "float32") -> Path:
    """An untrained policy file of the paper's size (the benches time its arithmetic)."""
    from qnav.sim.config import scenario
    from qnav.training.export import export_onnx, policy_contract
    from qnav.training.networks import QNetwork

    world = scenario("obstacles-inertia")
    network = QNetwork("recurrent", 720)
    policy = folder / f"paper-sized-{weight_type}.onnx"
    contract = policy_contract(network, world, 5, "untrained (bench)", "", weight_type=weight_type)
    export_onnx(network, contract, policy)
    return policy


def bench_controller(args: argparse.Namespace) -> int:
    """End-to-end latency of the controller daemon: scan published -> command received."""
    import tempfile

    from qnav.controller.bench_e2e import format_report, run
    from qnav.controller.policy import PolicyRuntime
    from qnav.sim.config import scenario
    from qnav.tracking import lookahead_settings, room_of

    rates = [float(r) for r in (args.rates or "5,50").split(",")]
    with tempfile.TemporaryDirectory() as scratch:
        policy = args.policy or _paper_sized_policy(Path(scratch), args.weights)
        lookahead, drive = None, None
        if args.lookahead != "off":
            contract = PolicyRuntime(policy, backend="numpy").contract
            world = scenario(contract.scenario)
            if args.rates is None:  # the look ahead on every scan: the policy's rate
                rates = [1.0 / contract.control_period_s]
            settings = lookahead_settings(args.lookahead)
            lookahead = room_of(world, settings)
            steps = max(round((args.seconds + 2) * rate) for rate in rates)
            drive = Path(scratch) / "drive.npz"
            bench_drive(world, steps).save(drive)
        report = run(policy, rates, args.seconds, lookahead=lookahead, drive=drive, cpu=args.cpu)
        if args.policy is None:
            report["policy"] = f"{PAPER_SIZED}, {args.weights} weights"
    print(json.dumps(report) if args.json else format_report(report))
    return 0


def bench_drive(world: WorldConfig, steps: int, seed: int = 1005) -> Drive:
    """`steps` scans of one car in `world`: the perception probe's drive (go-to-target with held
    random actions, as `qnav bench lookahead` drives), episodes one after another."""
    import numpy as np

    from qnav.controller.bench_e2e import Drive
    from qnav.sim.evaluate import WanderingGoToTarget
    from qnav.sim.world import BatchedWorld

    batched = BatchedWorld(world, 1, seed=seed)
    observation = batched.reset(seed)
    driver = WanderingGoToTarget(1, 0.3, seed)
    poses, targets, scans = [], [], []
    for _ in range(steps):
        assert observation.scan_m is not None  # the bench's policy reads a lidar
        poses.append(observation.pose[0])
        targets.append(observation.target_xy[0])
        scans.append(observation.scan_m[0])
        observation = batched.step(driver(observation.target_features())).observation
    return Drive(np.array(poses), np.array(targets), np.array(scans, dtype=np.float32))


def bench_cluster(args: argparse.Namespace) -> int:
    """`qnav bench cluster`: a small fixed study on 1 Ray worker, then on 2."""
    from qnav.cli import main
    from qnav.training.bench_cluster import format_report, run

    if args.repeats < 1:
        raise ConfigError(f"--repeats = {args.repeats}: give at least 1")
    report = run(main, args.repeats)
    print(json.dumps(report) if args.json else format_report(report))
    return 0


def bench_bridge(args: argparse.Namespace) -> int:
    """`qnav bench bridge`: command latency through the bridge and its failsafe stop's delay."""
    from qnav.firmware_bridge.bench import measure

    result = measure(
        commands=args.commands,
        stops=args.stops,
        output=args.output,
        timeout_s=args.timeout_s,
        baseline=args.baseline,
    )
    print(json.dumps(result.report()) if args.json else result.text())
    return 0


def add_benches(benches: Verbs) -> None:
    """`qnav bench sim|learner|policy|lookahead|controller|cluster|bridge`: their options."""
    _add_sim(benches)
    _add_learner(benches)
    _add_policy(benches)
    _add_lookahead(benches)
    _add_controller(benches)
    _add_cluster(benches)
    _add_bridge(benches)


def _add_sim(benches: Verbs) -> None:
    """`qnav bench sim`."""
    parser = verb(
        benches,
        bench_sim,
        "sim",
        help="simulator env-steps per second on one core",
    )
    world_options(parser, "obstacles-inertia")
    parser.add_argument(
        "--batches", default="1,16,64,256", help="comma-separated batch sizes (1,16,64,256)"
    )
    parser.add_argument(
        "--seconds", type=float, default=2.0, help="timed seconds per configuration (2)"
    )
    flag(parser, "--no-scaling", "skip beam/obstacle scaling")
    flag(
        parser,
        "--barn",
        "in BARN's worlds (the barn scenario, each world of the batch in a layout of its own), "
        "driven by random actions and by the planner given the map",
    )
    flag(parser, "--json", "print one JSON object")


def _add_learner(benches: Verbs) -> None:
    """`qnav bench learner`."""
    parser = verb(
        benches,
        bench_learner,
        "learner",
        help="one training iteration's GFLOP/s against the machine's matmul rate",
    )
    parser.add_argument(
        "--model", default="recurrent", choices=["recurrent", "feedforward"], help="Q-network"
    )
    parser.add_argument("--batch", type=int, default=256, help="batch size (256)")
    parser.add_argument("--repeats", type=int, default=10, help="timed iterations (10)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (2)")
    flag(parser, "--json", "print one JSON object")


def _add_policy(benches: Verbs) -> None:
    """`qnav bench policy`."""
    parser = verb(
        benches,
        bench_policy,
        "policy",
        help="per-decision latency of the onboard runtime, per backend, one thread",
    )
    bench_policy_file(parser)
    parser.add_argument(
        "--backends", default="onnxruntime,numpy", help="comma-separated (onnxruntime,numpy)"
    )
    parser.add_argument(
        "--decisions", type=int, default=3000, help="timed decisions per backend (3000)"
    )
    parser.add_argument(
        "--gap-ms",
        type=float,
        default=0.0,
        help="sleep before each timed decision, as a daemon waits between scans (0: back to "
        "back, caches warm; 20 or 200: the 50 Hz or 5 Hz case)",
    )
    flag(parser, "--json", "print one JSON object")


def _add_lookahead(benches: Verbs) -> None:
    """`qnav bench lookahead`."""
    parser = verb(
        benches,
        bench_lookahead,
        "lookahead",
        help="the controller's look ahead per decision: tracker update, shield forecast, plan",
    )
    world_options(parser, "obstacles-inertia")
    parser.add_argument("--decisions", type=int, default=2000, help="timed decisions (2000)")
    parser.add_argument(
        "--cars",
        type=int,
        default=20,
        help="cars driven side by side, each timed alone and all forecast at once (20)",
    )
    flag(parser, "--json", "print one JSON object")


def _add_controller(benches: Verbs) -> None:
    """`qnav bench controller`."""
    parser = verb(
        benches,
        bench_controller,
        "controller",
        help="end to end: scan published by one process to command received by another",
    )
    bench_policy_file(parser)
    parser.add_argument(
        "--rates",
        help="comma-separated scan rates in Hz (5,50; with --lookahead, the policy's own rate: "
        "the look ahead decides on every scan)",
    )
    parser.add_argument("--seconds", type=float, default=30.0, help="timed seconds per rate (30)")
    lookahead_option(parser, "in the daemon, on a drive through the simulated room: ")
    parser.add_argument(
        "--cpu", type=int, metavar="N", help="pin the daemon to core N (default: not pinned)"
    )
    flag(parser, "--json", "print one JSON object")


def _add_cluster(benches: Verbs) -> None:
    """`qnav bench cluster`."""
    parser = verb(
        benches,
        bench_cluster,
        "cluster",
        help="a small fixed study on 1 Ray worker, then on 2: wall times and ratio",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed pairs (3)")
    flag(parser, "--json", "print one JSON object")


def _add_bridge(benches: Verbs) -> None:
    """`qnav bench bridge`."""
    parser = verb(
        benches,
        bench_bridge,
        "bridge",
        help="command on zenoh to MAVLink on the wire, and the failsafe stop's delay",
    )
    parser.add_argument("--commands", type=int, default=1000, help="timed commands (1000)")
    parser.add_argument(
        "--output", default="manual", choices=["manual", "guided"], help="output mode (manual)"
    )
    parser.add_argument(
        "--timeout-s", type=float, default=0.5, help="failsafe.command_timeout_s (0.5)"
    )
    parser.add_argument("--stops", type=int, default=5, help="failsafe stops timed (5)")
    flag(
        parser,
        "--baseline",
        "also time a bare zenoh-to-UDP echo process: the floor this machine sets",
    )
    flag(parser, "--json", "print one JSON object")


def bench_policy_file(bench: argparse.ArgumentParser) -> None:
    """The policy a latency bench times: a file, or the paper-sized one in either weight type."""
    policy = bench.add_mutually_exclusive_group()
    policy.add_argument(
        "--policy",
        type=Path,
        default=None,
        help="policy file (default: an untrained paper-sized recurrent policy, exported here)",
    )
    policy.add_argument(
        "--weights",
        choices=WEIGHT_TYPES,
        default="float32",
        help="weights of the default paper-sized policy: float32 or int8 (float32)",
    )
