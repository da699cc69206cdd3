"""`qnav bench sim`: env-steps per second of the batched simulator on one core.

Throughput is measured in repeated timed chunks; the median over chunks is reported with the
slowest and fastest chunk, so one noisy moment does not decide the figure.
"""

from __future__ import annotations

import os
import platform
import time
from dataclasses import replace
from typing import Any

import numpy as np

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.observation import LidarSpec
from qnav.sim.config import WorldConfig
from qnav.sim.world import BatchedWorld


def pin_to_one_core() -> str:
    """Run on a single CPU (the first this process may use); returns a description."""
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to cpu {cpu}"
    return "not pinned (no sched_setaffinity on this platform)"


def steps_per_second(
    config: WorldConfig, batch: int, seconds: float = 2.0, chunks: int = 7, seed: int = 0
) -> dict[str, float]:
    """Median, min and max env-steps per second of a random agent over `chunks` timed chunks."""
    world = BatchedWorld(config, batch, seed=seed)
    actions = np.random.default_rng(seed).integers(0, NUM_ACTIONS, size=(256, batch))
    for row in actions[:5]:  # warm caches and lazily built tables
        world.step(row)
    # Size a chunk so that all chunks together take about `seconds`.
    start = time.perf_counter()
    world.step(actions[0])
    per_step = max(time.perf_counter() - start, 1e-6)
    steps_per_chunk = max(1, int(seconds / chunks / per_step))
    rates = []
    for chunk in range(chunks):
        start = time.perf_counter()
        for i in range(steps_per_chunk):
            world.step(actions[(chunk * steps_per_chunk + i) % len(actions)])
        rates.append(steps_per_chunk * batch / (time.perf_counter() - start))
    return {
        "steps_per_second": float(np.median(rates)),
        "min": float(np.min(rates)),
        "max": float(np.max(rates)),
    }


def run(
    config: WorldConfig,
    *,
    batches: tuple[int, ...] = (1, 16, 64, 256),
    beams: tuple[int, ...] = (90, 180, 360, 720, 1440),
    obstacles: tuple[int, ...] = (0, 1, 5, 10, 20),
    scaling_batch: int = 64,
    seconds: float = 2.0,
    pin: bool = True,
) -> dict[str, Any]:
    """The whole benchmark as one JSON-ready dict."""
    pinned = pin_to_one_core() if pin else "not pinned"
    results = [{"batch": b, **steps_per_second(config, b, seconds)} for b in batches]
    beam_results = []
    if config.lidar is not None:
        for count in beams:
            varied = replace(config, lidar=LidarSpec(count, config.lidar.max_range_m))
            beam_results.append(
                {"beams": count, **steps_per_second(varied, scaling_batch, seconds / 2)}
            )
    obstacle_results = []
    for count in obstacles:
        varied = replace(config, obstacles=replace(config.obstacles, count=count))
        obstacle_results.append(
            {"obstacles": count, **steps_per_second(varied, scaling_batch, seconds / 2)}
        )
    return {
        "scenario": config.name,
        "results": results,
        "beams": beam_results,
        "obstacles": obstacle_results,
        "scaling_batch": scaling_batch,
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "numpy": np.__version__,
            "affinity": pinned,
        },
    }


def format_table(report: dict[str, Any]) -> str:
    """The report as text tables."""
    lines = [
        f"scenario {report['scenario']}, one core ({report['machine']['affinity']})",
        "",
        f"{'batch':>6} {'steps/s (median)':>17} {'min':>10} {'max':>10}",
    ]
    lines += [
        f"{r['batch']:>6} {r['steps_per_second']:>17,.0f} {r['min']:>10,.0f} {r['max']:>10,.0f}"
        for r in report["results"]
    ]
    for key, label in (("beams", "beams"), ("obstacles", "obstacles")):
        if report[key]:
            lines += ["", f"{label:>9} {'steps/s at batch ' + str(report['scaling_batch']):>22}"]
            lines += [f"{r[key]:>9} {r['steps_per_second']:>22,.0f}" for r in report[key]]
    return "\n".join(lines)
