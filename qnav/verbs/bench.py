"""Handlers of `qnav bench`: simulator, learner, policy, look ahead, controller, cluster, bridge."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from qnav.contracts.errors import ConfigError
from qnav.sim.config import WorldConfig, load_world

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
    from qnav.tracking import lookahead_settings

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
            lookahead = replace(settings, room_size_m=world.arena.size_m)
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
