"""The paper's pictures of a policy: the action map (figure 3) and trajectories (figure 10)."""

from __future__ import annotations

import copy
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from numpy.typing import NDArray

from qnav.contracts.actions import Action
from qnav.contracts.motion import Outcome
from qnav.contracts.observation import distance_scale_m
from qnav.sim.config import WorldConfig
from qnav.sim.world import observe, reset, step
from qnav.training.agent import policy_agent
from qnav.training.networks import QNetwork

_ARROWS = {
    Action.FORWARD: ("^", "tab:blue", "forward"),
    Action.LEFT: ("<", "tab:green", "turn left"),
    Action.RIGHT: (">", "tab:red", "turn right"),
}


def action_grid(
    network: QNetwork,
    world: WorldConfig,
    window: int,
    half_width_m: float = 2.0,
    spacing_m: float = 0.4,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Greedy action with the target at the arena's centre and the robot facing +y at each cell.

    The robot has been standing still: its window holds k copies of the cell's observation.
    """
    cells = round(half_width_m / spacing_m)
    offsets = np.arange(-cells, cells + 1) * spacing_m
    gx, gy = np.meshgrid(offsets, offsets)
    centre = world.arena.size_m / 2
    n = gx.size
    world = replace(world, obstacles=replace(world.obstacles, count=0))
    state = reset(world, np.zeros(n, np.int64), np.zeros(n, np.int64))
    pose = np.stack([centre + gx.ravel(), centre + gy.ravel(), np.full(n, math.pi / 2)], axis=1)
    state = state._replace(pose=pose, target_xy=np.full((n, 2), centre))
    frames = observe(world, state).frames(distance_scale_m(world.lidar))
    with torch.no_grad():
        device = next(network.parameters()).device
        windows = torch.from_numpy(np.repeat(frames[:, None], window, axis=1)).to(device)
        q = network(windows).cpu().numpy()
    return gx, gy, q.argmax(axis=1).reshape(gx.shape)


def draw_action_maps(
    maps: list[tuple[str, tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]]],
    path: Path,
) -> Path:
    """Side-by-side action maps, as in the paper's figure 3."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(4.2 * len(maps), 4.4), dpi=100)
    FigureCanvasAgg(figure)
    for index, (title, (gx, gy, actions)) in enumerate(maps):
        axes = figure.add_subplot(1, len(maps), index + 1)
        for action, (marker, colour, label) in _ARROWS.items():
            chosen = actions == action
            axes.scatter(gx[chosen], gy[chosen], marker=marker, color=colour, s=60, label=label)
        axes.scatter([0], [0], marker="*", s=300, color="gold", edgecolor="k", label="target")
        axes.set_title(title)
        axes.set_xlabel("x (m) from target")
        axes.set_ylabel("y (m) from target")
        axes.set_aspect("equal")
        axes.grid(alpha=0.3)
        if index == 0:
            axes.legend(loc="lower left", fontsize=8)
    figure.suptitle("Greedy action, robot facing +y, target at the centre")
    figure.tight_layout()
    figure.savefig(path)
    return path


def trajectories(
    network: QNetwork,
    world: WorldConfig,
    window: int,
    starts: NDArray[np.float64],
    max_steps: int = 300,
) -> tuple[list[NDArray[np.float64]], NDArray[np.int64], NDArray[np.float64]]:
    """Greedy paths from start poses (S, 3) to a target at the arena's centre."""
    n = starts.shape[0]
    world = replace(world, obstacles=replace(world.obstacles, count=0), max_episode_steps=max_steps)
    centre = world.arena.size_m / 2
    target = np.array([centre, centre])
    state = reset(world, np.zeros(n, np.int64), np.zeros(n, np.int64))
    state = state._replace(pose=starts.copy(), target_xy=np.tile(target, (n, 1)))
    observation = observe(world, state)
    agent = policy_agent(network, world, n, window)
    agent.start(np.arange(n), np.zeros(n, np.int64))
    paths = [starts[:, :2].copy()]
    outcome = np.full(n, Outcome.RUNNING, dtype=np.int64)
    active = np.ones(n, dtype=bool)
    for _ in range(max_steps):
        state, observation, transition = step(world, state, agent.act(observation))
        paths.append(np.where(active[:, None], observation.pose[:, :2], paths[-1]))
        done = (transition.terminated | transition.truncated) & active
        outcome[done] = transition.outcome[done]
        active &= ~done
        if not active.any():
            break
    stacked = np.stack(paths, axis=1)
    return [stacked[i] for i in range(n)], outcome, target


def draw_trajectories(
    paths: list[NDArray[np.float64]],
    outcome: NDArray[np.int64],
    target: NDArray[np.float64],
    title: str,
    path: Path,
) -> Path:
    """Paths from several starts to the target, as in the paper's figure 10."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(5.2, 5.0), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    colours = {Outcome.SUCCESS: "tab:blue", Outcome.COLLISION: "tab:red", Outcome.RUNNING: "0.5"}
    for trace, result in zip(paths, outcome, strict=True):
        axes.plot(trace[:, 0], trace[:, 1], color=colours[Outcome(int(result))], lw=1.5)
        axes.plot(trace[0, 0], trace[0, 1], "o", color="k", ms=4)
    axes.plot(*target, marker="*", ms=20, color="gold", markeredgecolor="k")
    axes.set_aspect("equal")
    axes.grid(alpha=0.3)
    axes.set_xlabel("x (m)")
    axes.set_ylabel("y (m)")
    reached = int(np.sum(outcome == Outcome.SUCCESS))
    axes.set_title(f"{title}\n{reached} of {len(paths)} starts reach the target")
    figure.tight_layout()
    figure.savefig(path)
    return path


def ring_of_starts(
    world: WorldConfig, count: int = 12, radius_m: float = 2.5
) -> NDArray[np.float64]:
    """Start poses on a circle around the arena's centre, each facing away from the centre."""
    centre = world.arena.size_m / 2
    angles = np.linspace(0, 2 * math.pi, count, endpoint=False)
    return np.stack(
        [centre + radius_m * np.cos(angles), centre + radius_m * np.sin(angles), angles], axis=1
    )


def write_figures(run_dir: Path, out_dir: Path) -> list[Path]:
    """The action maps (earliest snapshot and final network) and trajectories of a run."""
    from qnav.training.run_folder import load_network

    network, run = load_network(run_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    name = f"{run.world.name}-{run.train.model}-seed{run.train.seed}"
    written = []
    maps = []
    snapshots = sorted((run_dir / "snapshots").glob("episodes-*.pt"))
    if snapshots:
        early = copy.deepcopy(network)
        saved = torch.load(snapshots[0], weights_only=False, map_location="cpu")
        early.load_state_dict(saved["online"])
        maps.append(
            (
                f"early: {saved['iterations']} iterations",
                action_grid(early, run.world, run.train.window),
            )
        )
    maps.append(("final", action_grid(network, run.world, run.train.window)))
    written.append(draw_action_maps(maps, out_dir / f"action-map-{name}.png"))
    paths, outcome, target = trajectories(
        network, run.world, run.train.window, ring_of_starts(run.world)
    )
    written.append(
        draw_trajectories(paths, outcome, target, name, out_dir / f"trajectories-{name}.png")
    )
    return written
