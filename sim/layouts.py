"""Static worlds: a floor of cylinders with its own start and goal each (BARN's kind of world).

A `Layouts` holds L worlds as padded arrays, so that a batch of N worlds, each in a layout of its
own, is one gather (`cylinders_of`). Cylinders a layout does not use are parked far outside any
lidar's reach, where they cover no beam and are never the nearest surface.

Where layouts come from (`sim.config.LayoutConfig.source`) is resolved once per process
(`layouts_of`): the committed BARN conversion, a folder in BARN's format, a conversion file, or
the generator's families (`sim.clutter`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.errors import ConfigError
from qnav.sim import rng
from qnav.sim.config import LayoutConfig

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

PARKED_M = 1.0e6
"""Where an unused cylinder slot sits (x = y = PARKED_M): beyond every lidar's range."""

_LAYOUT_STREAM = 17
"""The random stream of an episode's key that picks its layout (`sim.rng`)."""

FORMAT = "qnav-layouts-1"
"""The conversion file's format tag (`Layouts.save`)."""


@dataclass(frozen=True, eq=False)
class Layouts:
    """L static worlds of cylinders, each with a start pose, a goal and a reference path."""

    name: str
    """Where the layouts came from (for reports)."""
    cylinder_xy: F64
    """(L, K, 2) cylinder centres in metres; unused slots at (PARKED_M, PARKED_M)."""
    cylinder_count: I64
    """(L,) cylinders each layout uses (its first slots)."""
    cylinder_radius_m: float
    """Radius of every cylinder."""
    start_pose: F64
    """(L, 3) the robot's start: x, y in metres and heading in radians."""
    goal_xy: F64
    """(L, 2) the goal."""
    path_length_m: F64
    """(L,) length of a collision-free reference path from start to goal (BARN's metric divides
    it by the robot's top speed); NaN where none is known."""
    world_id: I64
    """(L,) each layout's number in its source (BARN's world index; a generator's draw)."""

    def __post_init__(self) -> None:
        count = self.cylinder_count.shape[0]
        shapes = {
            "cylinder_xy": (self.cylinder_xy.shape[0], self.cylinder_xy.shape[2:]),
            "start_pose": (self.start_pose.shape[0], self.start_pose.shape[1:]),
            "goal_xy": (self.goal_xy.shape[0], self.goal_xy.shape[1:]),
            "path_length_m": (self.path_length_m.shape[0], self.path_length_m.shape[1:]),
            "world_id": (self.world_id.shape[0], self.world_id.shape[1:]),
        }
        expected = {
            "cylinder_xy": (count, (2,)),
            "start_pose": (count, (3,)),
            "goal_xy": (count, (2,)),
            "path_length_m": (count, ()),
            "world_id": (count, ()),
        }
        for key, shape in shapes.items():
            if shape != expected[key]:
                raise ConfigError(f"layouts {self.name!r}: {key} has shape {shape}, not {expected}")
        if count == 0:
            raise ConfigError(f"layouts {self.name!r}: no layouts")

    def __len__(self) -> int:
        return int(self.cylinder_count.shape[0])

    @property
    def most_cylinders(self) -> int:
        """K: the slots each layout has."""
        return int(self.cylinder_xy.shape[1])

    def cylinders_of(self, layout: I64) -> F64:
        """(N, K, 2) the cylinders of each world's layout (N,)."""
        return self.cylinder_xy[layout]

    def take(self, index: I64, name: str | None = None) -> Layouts:
        """The layouts `index`, in that order, their slots trimmed to the most they use."""
        counts = self.cylinder_count[index]
        slots = int(counts.max())
        return Layouts(
            name=self.name if name is None else name,
            cylinder_xy=self.cylinder_xy[index, :slots],
            cylinder_count=counts,
            cylinder_radius_m=self.cylinder_radius_m,
            start_pose=self.start_pose[index],
            goal_xy=self.goal_xy[index],
            path_length_m=self.path_length_m[index],
            world_id=self.world_id[index],
        )

    @cached_property
    def boxes(self) -> F64:
        """(L, 2, 2) each layout's box (lowest x, y; highest x, y) round its cylinders, start
        and goal: where its moving obstacles move."""
        used = self.cylinder_xy[..., 0] < PARKED_M
        low = np.where(used[..., None], self.cylinder_xy, np.inf).min(axis=1)
        high = np.where(used[..., None], self.cylinder_xy, -np.inf).max(axis=1)
        ends = np.stack([self.start_pose[:, :2], self.goal_xy], axis=1)
        return np.stack(
            [np.minimum(low, ends.min(axis=1)), np.maximum(high, ends.max(axis=1))], axis=1
        )

    def box(self) -> F64:
        """(2, 2) the corners (lowest x, y; highest x, y) of the box that holds every layout's
        cylinders, starts and goals."""
        used = self.cylinder_xy[self.cylinder_xy[..., 0] < PARKED_M]
        points = np.vstack([used, self.start_pose[:, :2], self.goal_xy])
        return np.stack([points.min(axis=0), points.max(axis=0)])

    def save(self, path: Path, provenance: dict[str, str]) -> None:
        """Write one compressed file (numpy's npz): the arrays, centres to the millimetre, and
        `provenance` (source, commit, licence) as JSON beside them."""
        centres_mm = np.round(self.cylinder_xy * 1000.0)
        centres_mm[self.cylinder_xy >= PARKED_M] = np.iinfo(np.int32).max
        np.savez_compressed(
            path,
            format=np.array(FORMAT),
            name=np.array(self.name),
            provenance=np.array(json.dumps(provenance, sort_keys=True)),
            cylinder_mm=centres_mm.astype(np.int32),
            cylinder_count=self.cylinder_count,
            cylinder_radius_m=np.array(self.cylinder_radius_m),
            start_pose=self.start_pose,
            goal_xy=self.goal_xy,
            path_length_m=self.path_length_m,
            world_id=self.world_id,
        )


def load_layouts(path: Path) -> tuple[Layouts, dict[str, str]]:
    """A conversion file written by `Layouts.save`, and its provenance."""
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as error:
        raise ConfigError(f"layouts file {path}: cannot be read ({error})") from None
    with data:
        if "format" not in data.files or str(data["format"]) != FORMAT:
            raise ConfigError(f"layouts file {path}: not a {FORMAT} file")
        centres_mm = data["cylinder_mm"]
        centres = np.where(
            centres_mm == np.iinfo(np.int32).max, PARKED_M, centres_mm.astype(np.float64) / 1000.0
        )
        layouts = Layouts(
            name=str(data["name"]),
            cylinder_xy=centres,
            cylinder_count=data["cylinder_count"].astype(np.int64),
            cylinder_radius_m=float(data["cylinder_radius_m"]),
            start_pose=data["start_pose"].astype(np.float64),
            goal_xy=data["goal_xy"].astype(np.float64),
            path_length_m=data["path_length_m"].astype(np.float64),
            world_id=data["world_id"].astype(np.int64),
        )
        provenance: dict[str, str] = json.loads(str(data["provenance"]))
    return layouts, provenance


def stack_layouts(
    *,
    name: str,
    cylinders: list[F64],
    radius_m: float,
    start_pose: F64,
    goal_xy: F64,
    path_length_m: F64,
    world_id: I64,
) -> Layouts:
    """Layouts from one (K_i, 2) array of cylinder centres per world, padded to the largest."""
    slots = max(len(c) for c in cylinders)
    xy = np.full((len(cylinders), slots, 2), PARKED_M)
    for row, centres in enumerate(cylinders):
        xy[row, : len(centres)] = centres
    return Layouts(
        name=name,
        cylinder_xy=xy,
        cylinder_count=np.array([len(c) for c in cylinders], dtype=np.int64),
        cylinder_radius_m=radius_m,
        start_pose=np.asarray(start_pose, dtype=np.float64),
        goal_xy=np.asarray(goal_xy, dtype=np.float64),
        path_length_m=np.asarray(path_length_m, dtype=np.float64),
        world_id=np.asarray(world_id, dtype=np.int64),
    )


@cache
def layouts_of(layout: LayoutConfig) -> Layouts | None:
    """The layouts `layout.source` names, read or generated once per process (None: the paper's
    room)."""
    from qnav.sim import barn, clutter

    source = layout.source
    if not source:
        return None
    families = source.split("+")
    if all(family in clutter.FAMILIES for family in families):
        return clutter.generated_layouts(tuple(families), layout.split, layout.worlds)
    path = barn.BARN_FILE if source == "barn" else Path(source)
    if source == "barn" and not path.is_file():
        raise ConfigError(f"layout.source = 'barn': the conversion {path} is missing")
    if path.is_dir():
        read = barn.read_barn_folder(path)
    elif path.is_file():
        read = load_layouts(path)[0]
    else:
        read = None
    if read is not None:
        return read if layout.worlds >= len(read) else read.take(np.arange(layout.worlds))
    raise ConfigError(
        f"layout.source = {source!r}: not 'barn', a family ({', '.join(clutter.FAMILIES)}, "
        "joined by +), a BARN-format folder or a conversion file"
    )


def layout_indices(layout: LayoutConfig, count: int, keys: NDArray[np.uint64], episode: I64) -> I64:
    """(N,) the layout of each episode: episode mod `count` ("cycle") or a uniform draw from
    the episode's key ("random")."""
    if layout.order == "cycle":
        return np.asarray(episode, dtype=np.int64) % count
    draw = rng.uniform(keys, _LAYOUT_STREAM, ())
    return np.minimum((draw * count).astype(np.int64), count - 1)
