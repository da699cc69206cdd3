"""`qnav bench sim`: env-steps per second of the batched simulator on one core.

Throughput is measured in repeated timed chunks; the median over chunks is reported with the
slowest and fastest chunk, so one noisy moment does not decide the figure. Only
`BatchedWorld.step` is timed, automatic resets included; a driver chooses each step's actions
outside the clock: random actions, or in BARN's worlds (`--barn`) the planner given the map, so
that the robots cross the clutter as a trained policy does rather than idle at the start.

What a user's loop gets differs by two things the table shows beside each rate: the driver's
own time per step (a network's forward pass, go-to-target's few operations), which the clock
leaves out, and the episodes' length: every step where some world's episode ends pays for a
reset of those worlds and a copy of the whole batch's state, so drivers whose episodes end
sooner (go-to-target collides within about 16 steps in walls-increment, the random driver
lasts about 72) get fewer steps per second (docs/simulator.md, "Speed").
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.observation import LidarSpec
from qnav.sim.config import WorldConfig
from qnav.sim.evaluate import Agent, GoToTargetAgent
from qnav.sim.raycast import COMPILED
from qnav.sim.world import BatchedWorld, Observation


def pin_to_one_core() -> str:
    """Run on a single CPU (the first this process may use); returns a description."""
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to cpu {cpu}"
    return "not pinned (no sched_setaffinity on this platform)"


def steps_per_second(
    config: WorldConfig,
    batch: int,
    seconds: float = 2.0,
    *,
    chunks: int = 7,
    seed: int = 0,
    driver: Agent | None = None,
) -> dict[str, float]:
    """Median, min and max env-steps per second over `chunks` timed chunks of `BatchedWorld.step`
    alone, the actions chosen off the clock by `driver` (random without one); also the mean
    episode length (steps per episode ended) and the driver's seconds per step."""
    world = BatchedWorld(config, batch, seed=seed)
    observation = world.reset(seed=seed)
    chance = np.random.default_rng(seed)
    ids = np.arange(batch)

    def act(observation: Observation) -> NDArray[np.int64]:
        if driver is None:
            return chance.integers(0, NUM_ACTIONS, size=batch)
        return driver.act(observation)

    if driver is not None:
        driver.start(ids, world.state.episode)
    timed = {"step": 0.0, "driver": 0.0, "steps": 0, "ended": 0}

    def advance() -> None:
        nonlocal observation
        before = time.perf_counter()
        action = act(observation)
        start = time.perf_counter()
        result = world.step(action)
        timed["step"] += time.perf_counter() - start
        timed["driver"] += start - before
        timed["steps"] += 1
        ended = np.flatnonzero(result.transition.terminated | result.transition.truncated)
        timed["ended"] += ended.size
        if driver is not None and ended.size:
            driver.start(ended, world.state.episode[ended])
        observation = result.observation

    for _ in range(5):  # warm caches and lazily built tables
        advance()
    per_step = max(timed["step"] / 5, 1e-6)
    # Size a chunk so that all chunks together take about `seconds` of stepping.
    steps_per_chunk = max(1, int(seconds / chunks / per_step))
    rates = []
    timed = {"step": 0.0, "driver": 0.0, "steps": 0, "ended": 0}
    for _ in range(chunks):
        before = timed["step"]
        for _ in range(steps_per_chunk):
            advance()
        rates.append(steps_per_chunk * batch / (timed["step"] - before))
    return {
        "steps_per_second": float(np.median(rates)),
        "min": float(np.min(rates)),
        "max": float(np.max(rates)),
        "episode_steps": timed["steps"] * batch / max(1, timed["ended"]),
        "driver_s_per_step": timed["driver"] / timed["steps"],
    }


Drivers = dict[str, Callable[[int], Agent | None]]
"""Named drivers of the timed loop, each made for a batch size (None: random actions)."""


def default_drivers(config: WorldConfig) -> Drivers:
    """Random actions, and a driver that crosses the world as a good policy would: in worlds of
    layouts the planner given the map, else go-to-target."""
    if config.layout.source:
        from qnav.sim.mapplan import MapPlanner

        planner = MapPlanner(config)
        return {"random": lambda _: None, "map planner": lambda _: planner}
    return {"random": lambda _: None, "go-to-target": lambda _: GoToTargetAgent()}


def run(
    config: WorldConfig,
    *,
    batches: tuple[int, ...] = (1, 16, 64, 256),
    beams: tuple[int, ...] = (90, 180, 360, 720, 1440),
    obstacles: tuple[int, ...] = (0, 1, 5, 10, 20),
    scaling_batch: int = 64,
    seconds: float = 2.0,
    pin: bool = True,
    drivers: Drivers | None = None,
) -> dict[str, Any]:
    """The whole benchmark as one JSON-ready dict: each batch size with each driver, then the
    random driver's rate by beams and by obstacles (none in worlds of layouts)."""
    pinned = pin_to_one_core() if pin else "not pinned"
    drivers = drivers if drivers is not None else default_drivers(config)
    results = [
        {"batch": b, "driver": name, **steps_per_second(config, b, seconds, driver=make(b))}
        for b in batches
        for name, make in drivers.items()
    ]
    beam_results = []
    if config.lidar is not None:
        for count in beams:
            varied = replace(config, lidar=LidarSpec(count, config.lidar.max_range_m))
            beam_results.append(
                {"beams": count, **steps_per_second(varied, scaling_batch, seconds / 2)}
            )
    obstacle_results = []
    for count in obstacles if not config.layout.source else ():
        varied = replace(config, obstacles=replace(config.obstacles, count=count))
        obstacle_results.append(
            {"obstacles": count, **steps_per_second(varied, scaling_batch, seconds / 2)}
        )
    return {
        "scenario": config.name,
        "lidar": "compiled" if COMPILED else "numpy",
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
        f"scenario {report['scenario']}, one core ({report['machine']['affinity']}), "
        f"{report['lidar']} lidar among many circles; only the simulator's step is timed",
        "",
        f"{'batch':>6} {'driver':<13} {'steps/s (median)':>17} {'min':>9} {'max':>9} "
        f"{'steps/episode':>14} {'driver ms/step':>15}",
    ]
    lines += [
        f"{r['batch']:>6} {r['driver']:<13} {r['steps_per_second']:>17,.0f} {r['min']:>9,.0f} "
        f"{r['max']:>9,.0f} {r['episode_steps']:>14.1f} {1000 * r['driver_s_per_step']:>15.2f}"
        for r in report["results"]
    ]
    for key, label in (("beams", "beams"), ("obstacles", "obstacles")):
        if report[key]:
            lines += ["", f"{label:>9} {'steps/s at batch ' + str(report['scaling_batch']):>22}"]
            lines += [f"{r[key]:>9} {r['steps_per_second']:>22,.0f}" for r in report[key]]
    return "\n".join(lines)
