"""Collected episodes, and their files: one per collection round, so a killed run loses none.

Each file is written to a temporary name and renamed, so a file either holds a whole round or
does not exist.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray


class Episode(NamedTuple):
    """One finished episode, as collected."""

    pose: NDArray[np.float64]
    """(T + 1, 3) poses from the first observation to the last."""
    scan_m: NDArray[np.float32] | None
    """(T + 1, B) raw ranges in metres, or None without a lidar."""
    clearance_m: NDArray[np.float64]
    """(T + 1,) distance to the nearest surface at each observation."""
    action: NDArray[np.int64]
    """(T,) actions taken."""
    target_xy: NDArray[np.float64]
    """(2,) the episode's own target."""
    outcome: int
    """How it ended (sim.task.Outcome; RUNNING = truncated)."""
    obstacle_xy: NDArray[np.float64] | None = None
    """(T + 1, M, 2) obstacle centres at each observation (None: not kept)."""
    obstacle_velocity: NDArray[np.float64] | None = None
    """(T + 1, M, 2) obstacle velocities at each observation (None: not kept)."""


def write_round(folder: Path, round_index: int, episodes: list[Episode]) -> Path:
    """Store the episodes of one round as `round-000042.npz`."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"round-{round_index:06d}.npz"
    partial = folder / f".round-{round_index:06d}.partial.npz"
    has_scan = episodes[0].scan_m is not None
    arrays: dict[str, NDArray[Any]] = {
        "lengths": np.array([e.action.size for e in episodes]),
        "pose": np.concatenate([e.pose for e in episodes]),
        "scan": np.concatenate([e.scan_m for e in episodes if e.scan_m is not None])
        if has_scan
        else np.zeros((0, 0), np.float32),
        "clearance": np.concatenate([e.clearance_m for e in episodes]),
        "action": np.concatenate([e.action for e in episodes]),
        "target": np.stack([e.target_xy for e in episodes]),
        "outcome": np.array([e.outcome for e in episodes]),
    }
    centres = [e.obstacle_xy for e in episodes if e.obstacle_xy is not None]
    velocities = [e.obstacle_velocity for e in episodes if e.obstacle_velocity is not None]
    if len(centres) == len(velocities) == len(episodes):
        arrays["obstacle_xy"] = np.concatenate(centres)
        arrays["obstacle_velocity"] = np.concatenate(velocities)
    np.savez(partial, **arrays)  # type: ignore[arg-type]  # (numpy's stub types **kwds as its allow_pickle)
    partial.replace(path)
    return path


def read_rounds(folder: Path) -> list[list[Episode]]:
    """Every stored round, in order."""
    rounds = []
    for path in sorted(folder.glob("round-*.npz")):
        with np.load(path) as stored:
            # Each read of an npz member loads the whole array again: read each once, and copy
            # each episode's part out of it, so no episode keeps the whole round alive.
            data = {name: stored[name] for name in stored.files}
            lengths = data["lengths"]
            frame_ends = np.cumsum(lengths + 1)
            action_ends = np.cumsum(lengths)
            has_scan = data["scan"].size > 0
            # Rounds written before obstacles were kept (2026-12-04) have none.
            has_obstacles = "obstacle_xy" in data
            # Rounds written while demonstrations existed (up to commit b8dfe92) also hold a
            # `demonstrated` flag per episode: runs that used them cannot resume
            # (`training.run_folder.read_settings`), and the flag is ignored.
            episodes = []
            for i, length in enumerate(lengths):
                frames = slice(frame_ends[i] - length - 1, frame_ends[i])
                episodes.append(
                    Episode(
                        pose=data["pose"][frames].copy(),
                        scan_m=data["scan"][frames].copy() if has_scan else None,
                        clearance_m=data["clearance"][frames].copy(),
                        action=data["action"][action_ends[i] - length : action_ends[i]].copy(),
                        target_xy=data["target"][i].copy(),
                        outcome=int(data["outcome"][i]),
                        obstacle_xy=data["obstacle_xy"][frames].copy() if has_obstacles else None,
                        obstacle_velocity=(
                            data["obstacle_velocity"][frames].copy() if has_obstacles else None
                        ),
                    )
                )
            rounds.append(episodes)
    return rounds
