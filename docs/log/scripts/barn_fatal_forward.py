"""Gauge: the states of stored cave episodes where driving forward is fatal, and how well a
network's choices fit the planner's labels there, against everywhere.

    .venv/bin/python docs/log/scripts/barn_fatal_forward.py RUN[,RUN...] [WEIGHTS.pt]

A state is *fatal for forward* when, after one forward step, every action held for
`HORIZON_STEPS - 1` more steps brings the robot's disc within a cylinder: the point of no
return of `barn_no_return.py`, where 38 of 41 collisions on 512 validation caves began (the
network drove forward, the planner turned). Stored episodes keep poses but not velocities, so
each episode is replayed from its start (layout found from the start pose) with the action that
reproduces each next pose. Flags are cached in /tmp/g/fatal-RUNNAME.npy in the order of the
run's stored transitions (the rounds' episodes in order), for later runs.
With WEIGHTS, the network's agreement with the labels on fatal states and elsewhere, on the
run's data and on the validation set of `barn_offline_bc.py` (/tmp/g/valset).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import step_robot
from qnav.sim.config import WorldConfig
from qnav.sim.layouts import Layouts, layouts_of
from qnav.training.episode_log import Episode, read_rounds

HORIZON_STEPS = 5
"""Steps (1 s) within which a fatal forward step ends in a collision whatever follows."""
F64 = NDArray[np.float64]


def gap_m(xy: F64, cylinders: F64, radius_m: float) -> F64:
    """(N,) distance from each point (N, 2) to the nearest of its cylinders (N, K, 2)."""
    d = np.sqrt(((cylinders - xy[:, None, :]) ** 2).sum(-1))  # unused slots are parked far
    return np.asarray(d.min(axis=1) - radius_m)


def replay_velocities(world: WorldConfig, episode: Episode) -> F64:
    """(T + 1, 2) velocities along a stored episode, the executed actions found step by step."""
    pose = episode.pose
    velocity = np.zeros((pose.shape[0], 2))
    for t in range(pose.shape[0] - 1):
        here = np.repeat(pose[t : t + 1], 3, axis=0)
        moved, speeds = step_robot(
            here, np.repeat(velocity[t : t + 1], 3, axis=0), np.arange(3), world.dynamics,
            world.control_period_s,
        )
        miss = np.abs(moved - pose[t + 1]).sum(axis=1)
        assert miss.min() < 1e-6, f"no action reproduces step {t}: {miss.min()}"
        velocity[t + 1] = speeds[int(np.argmin(miss))]
    return velocity


def fatal_forward(
    world: WorldConfig, layouts: Layouts, episode: Episode, layout: int | None = None
) -> NDArray[np.bool_]:
    """(T,) whether forward is fatal at each labelled state of a stored episode (its layout found
    from its start pose where not given: training layouts start apart, validation ones alike)."""
    if layout is None:
        miss = np.abs(layouts.start_pose[:, :2] - episode.pose[0, :2]).sum(axis=1)
        assert np.sum(miss < 1e-9) == 1, "the start pose does not tell the layout"
        layout = int(np.argmin(miss))
    pose, velocity = episode.pose[:-1], replay_velocities(world, episode)[:-1]
    n = pose.shape[0]
    cylinders = np.repeat(layouts.cylinders_of(np.array([layout])), n, axis=0)
    reach = world.robot_radius_m + layouts.cylinder_radius_m
    first, speed = step_robot(pose, velocity, np.zeros(n, np.int64), world.dynamics, world.control_period_s)
    hit_first = gap_m(first[:, :2], cylinders, reach) < 0
    every_hits = np.ones(n, dtype=bool)
    for action in range(3):
        p, v, hit = first, speed, hit_first.copy()
        for _ in range(HORIZON_STEPS - 1):
            p, v = step_robot(p, v, np.full(n, action, np.int64), world.dynamics, world.control_period_s)
            hit |= gap_m(p[:, :2], cylinders, reach) < 0
        every_hits &= hit
    return every_hits


def cached_flags(
    name: str, world: WorldConfig, episodes: list[Episode], layout_of_episode: bool = False
) -> NDArray[np.bool_]:
    """The episodes' flags, in their order, kept in /tmp/g/fatal-NAME.npy (each episode's layout
    found from its start pose, or with `layout_of_episode` its index: a validation round of
    order "cycle" runs layout i in episode i)."""
    cache = Path(f"/tmp/g/fatal-{name}.npy")
    if cache.exists():
        return np.load(cache)
    layouts = layouts_of(world.layout)
    assert layouts is not None
    flags = np.concatenate(
        [fatal_forward(world, layouts, e, i if layout_of_episode else None) for i, e in enumerate(episodes)]
    )
    cache.parent.mkdir(parents=True, exist_ok=True)
    np.save(cache, flags)
    return flags


def agreement(weights: Path, world: WorldConfig, episodes: list[Episode], flags: NDArray[np.bool_]) -> str:
    """The network's agreement with the stored labels on fatal states, and on the others."""
    import torch

    from qnav.training.networks import make_network
    from qnav.training.replay import EpisodeReplay
    from qnav.training.run_folder import read_settings

    train = read_settings(Path("runs/cave/dagger-recurrent-seed0")).train
    network = make_network(world, train)
    network.load_state_dict(torch.load(weights, weights_only=True)["online"])
    network.eval()
    data = EpisodeReplay(world, sum(len(e.action) + 1 for e in episodes) + 10, train.window)
    for e in episodes:
        data.add(e)
    stored = data.transitions()
    assert stored.size == flags.size, (stored.size, flags.size)
    rng = np.random.default_rng(0)
    parts = []
    for name, chosen in (("fatal", stored[flags]), ("other", rng.choice(stored[~flags], 12000))):
        if chosen.size == 0:
            continue
        with torch.no_grad():
            logits = torch.cat([network(torch.from_numpy(data.windows(c))) for c in np.array_split(chosen, max(1, chosen.size // 1000))])
        prob = torch.softmax(logits, 1).numpy()
        labels = data.action[chosen]
        agree = float((prob.argmax(1) == labels).mean())
        forward = float((prob.argmax(1) == 0).mean())
        parts.append(f"{name} n={chosen.size} agree {agree:.3f} forward chosen {forward:.3f}"
                     f" p(label) {prob[np.arange(labels.size), labels].mean():.3f}")
    return "; ".join(parts)


def main() -> None:
    from dataclasses import replace

    import torch

    from qnav.training.run_folder import read_settings

    torch.set_num_threads(1)
    runs = [Path(r) for r in sys.argv[1].split(",")]
    weights = Path(sys.argv[2]) if len(sys.argv) > 2 else None
    for run in runs:
        world = read_settings(run).world
        episodes = [e for r in read_rounds(run / "imitation") for e in r]
        flags = cached_flags(run.name, world, episodes)
        print(f"{run.name}: {flags.size} states, fatal for forward {flags.sum()} ({flags.mean():.4f})", flush=True)
        if weights:
            print("  train:", agreement(weights, world, episodes, flags), flush=True)
    if weights:
        world = read_settings(runs[0]).world
        val = replace(world, layout=replace(world.layout, split="validation", worlds=128, order="cycle"))
        rounds = read_rounds(Path("/tmp/g/valset"))
        for index, name in ((0, "the network's paths"), (1, "the planner's paths")):
            flags = cached_flags(f"valset{index}", val, rounds[index], layout_of_episode=True)
            print(f"  validation, {name}: fatal {flags.sum()};", agreement(weights, val, rounds[index], flags), flush=True)


if __name__ == "__main__":
    main()
