"""Gauge: how much of the planner's choice the robot's own sensing can tell, on the planner's
paths in 128 generated validation caves (never BARN's; the set of `barn_offline_bc.py`,
/tmp/g/valset round 1).

    .venv/bin/python docs/log/scripts/barn_seen_planner.py [STATES=600]

At a sample of states, the planner given the map is run again on a map of only the cylinders
the lidar has hit (unseen space free, as a mapping robot would plan): those hit by the current
scan (*visible now*: what a memoryless student can know), by the last 5 scans (*window*: the
network's 1 s), and by every scan since the episode's start (*seen so far*: what memory plus the
motion-capture pose could know). Its agreement with the full planner's label bounds what an
imitator with that information can reach; the network's agreement on these states is 0.76-0.80.
"""

from __future__ import annotations

import copy
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.sim.layouts import Layouts, layouts_of
from qnav.sim.mapplan import MapPlanner, cost_to_go
from qnav.training.episode_log import Episode, read_rounds
from qnav.training.run_folder import read_settings

HIT_M = 0.02
"""A beam's end within this of a cylinder's surface hit that cylinder."""


def hit_cylinders(episode: Episode, frames: range, centres: NDArray[np.float64], radius_m: float, angles: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(K,) the cylinders any beam of the episode's `frames` ended on."""
    seen = np.zeros(centres.shape[0], dtype=bool)
    for t in frames:
        scan = episode.scan_m[t].astype(np.float64)  # type: ignore[index]
        x, y, heading = episode.pose[t]
        ok = np.isfinite(scan)
        ends = np.stack([x + scan[ok] * np.cos(heading + angles[ok]), y + scan[ok] * np.sin(heading + angles[ok])], -1)
        gap = np.linalg.norm(ends[:, None, :] - centres[None], axis=-1) - radius_m
        nearest = gap.argmin(axis=1)
        seen[nearest[gap[np.arange(nearest.size), nearest] < HIT_M]] = True
    return seen


def planner_on(world, planner: MapPlanner, layouts: Layouts, layout: int, keep: NDArray[np.bool_], pose: NDArray[np.float64]) -> int:  # type: ignore[no-untyped-def]
    """The planner's action at `pose` on a map of the kept cylinders only."""
    count = int(layouts.cylinder_count[layout])
    centres = layouts.cylinder_xy[layout, :count][keep]
    one = Layouts(
        name="seen", cylinder_xy=centres[None], cylinder_count=np.array([centres.shape[0]]),
        cylinder_radius_m=layouts.cylinder_radius_m, start_pose=layouts.start_pose[layout][None],
        goal_xy=layouts.goal_xy[layout][None], path_length_m=np.array([np.nan]), world_id=np.array([0]),
    )
    grid = cost_to_go(one, 0, world.robot_radius_m, world.reach_m, planner.settings)
    sub = copy.copy(planner)  # the same settings and directions, this one map
    sub.layouts, sub._grids = one, {0: grid}
    return int(sub.act_at(pose[None], np.array([0]))[0])


def main() -> None:
    count = int(sys.argv[1]) if len(sys.argv) > 1 else 600
    base = read_settings(Path("runs/cave/dagger-recurrent-seed0")).world
    world = replace(base, layout=replace(base.layout, split="validation", worlds=128, order="cycle"))
    layouts = layouts_of(world.layout)
    assert layouts is not None and world.lidar is not None
    planner = MapPlanner(world)
    angles = world.lidar.beam_angles_rad()
    episodes = read_rounds(Path("/tmp/g/valset"))[1]
    rng = np.random.default_rng(0)
    picks = [(e, int(rng.integers(0, len(episodes[e].action)))) for e in rng.integers(0, len(episodes), count)]
    agree = {"full map (check)": 0, "visible now": 0, "window (5 scans)": 0, "seen so far": 0}
    started = time.perf_counter()
    for n, (e, t) in enumerate(picks, 1):
        episode, layout = episodes[e], int(e)
        centres = layouts.cylinder_xy[layout, : int(layouts.cylinder_count[layout])]
        label = int(episode.action[t])
        sets = {
            "full map (check)": np.ones(centres.shape[0], dtype=bool),
            "visible now": hit_cylinders(episode, range(t, t + 1), centres, layouts.cylinder_radius_m, angles),
            "window (5 scans)": hit_cylinders(episode, range(max(0, t - 4), t + 1), centres, layouts.cylinder_radius_m, angles),
            "seen so far": hit_cylinders(episode, range(0, t + 1), centres, layouts.cylinder_radius_m, angles),
        }
        for name, keep in sets.items():
            agree[name] += planner_on(world, planner, layouts, layout, keep, episode.pose[t]) == label
        if n % 100 == 0 or n == len(picks):
            shares = ", ".join(f"{k} {v / n:.3f}" for k, v in agree.items())
            print(f"{n} states ({time.perf_counter() - started:.0f} s): {shares}", flush=True)


if __name__ == "__main__":
    main()
