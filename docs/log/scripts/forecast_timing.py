# Ad hoc measurement of issue 53 (2026-12-07); runs against the commit that wrote the forecast's
# robot paths out (contracts/lookahead.py: robot_paths), and later.
"""The shield's forecast (`contracts.lookahead.collision_shares`) of the working tree against the
one at an older commit, back to back on the same states, in this process: one car at a time as
the controller forecasts (the states of `qnav bench controller --lookahead shield`'s drive, 150
decisions, three rounds) and 64 cars at once as the lab's evaluations do; the shares must be
equal. Median and 99th percentile milliseconds (one car), best of three seconds (64 cars).

Usage: forecast_timing.py OLD_COMMIT   (e.g. c2ac6f6, before the change)
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np

import qnav.contracts.lookahead as new
from qnav.controller.lookahead import LookaheadSettings, beliefs_of
from qnav.controller.perception import TrackerSettings
from qnav.sim.config import scenario
from qnav.tracking import world_lookahead
from qnav.verbs.bench import bench_drive


def at_commit(commit: str, folder: Path) -> ModuleType:
    """contracts/lookahead.py as it was at `commit`, imported as a module of its own."""
    source = subprocess.run(
        ["git", "show", f"{commit}:contracts/lookahead.py"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    path = folder / "old_lookahead.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("old_lookahead", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> None:
    world = scenario("obstacles-inertia")
    settings = LookaheadSettings(room_size_m=world.arena.size_m)
    with tempfile.TemporaryDirectory() as scratch:
        old = at_commit(sys.argv[1], Path(scratch))
        drive = bench_drive(world, 170)
        car = world_lookahead(world, settings, TrackerSettings())
        states = []
        for i in range(len(drive.poses)):
            now = i * world.control_period_s
            car.observe(now, drive.poses[i], now, drive.scans[i])
            if i >= 20:
                states.append((beliefs_of([car], [drive.targets[i]]), car.continuations()))
        times: dict[str, list[float]] = {"old": [], "new": []}
        for _ in range(3):
            for belief, tails in states:
                shares = []
                for name, module in (("old", old), ("new", new)):
                    started = time.perf_counter()
                    shares.append(module.collision_shares(car.model, belief, tails))
                    times[name].append((time.perf_counter() - started) * 1e3)
                assert np.array_equal(*shares)
        for name, values in times.items():
            p50, p99 = np.percentile(values, [50, 99])
            print(f"one car, {name}: p50 {p50:.2f} ms, p99 {p99:.2f} ms")
        cars = [world_lookahead(world, settings, TrackerSettings()) for _ in range(64)]
        for row, one in enumerate(cars):
            for k in range(3):
                j = 3 * row + k
                one.observe(
                    k * 0.2,
                    drive.poses[j % len(drive.poses)],
                    k * 0.2,
                    drive.scans[j % len(drive.poses)],
                )
        belief = beliefs_of(
            cars, [drive.targets[(3 * row + 2) % len(drive.poses)] for row in range(64)]
        )
        tails = np.concatenate([one.continuations() for one in cars])
        best: dict[str, float] = {"old": np.inf, "new": np.inf}
        for _ in range(3):
            for name, module in (("old", old), ("new", new)):
                started = time.perf_counter()
                module.collision_shares(cars[0].model, belief, tails)
                best[name] = min(best[name], time.perf_counter() - started)
        print(f"64 cars at once: old {best['old']:.3f} s, new {best['new']:.3f} s")


if __name__ == "__main__":
    main()
