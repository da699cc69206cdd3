"""BARN (Perille et al. 2020; the ICRA BARN Challenge): its world files, its protocol, its metric.

A folder in BARN's format holds `world_N.world` (Gazebo SDF: static cylinders) and, beside them,
`path_files/path_N.npy` (the generator's collision-free path, in grid cells). The challenge's
`run.py` (Daffan/the-barn-challenge) fixes the protocol read here:

- start (-2.25, 3) heading +y: the value `run.py` sets for BARN worlds in its `__main__` (its
  module default and `report_test.py` say -2); the goal is the start plus (0, 10);
- success within 1 m of the goal; a collision ends the run; 100 s is a timeout;
- path cell (r, c) lies at (0.15 r - 4.575, 0.15 c + 5.075) (`path_coord_to_gazebo_coord`), and
  the path's length runs start -> cells -> goal;
- metric = success x T / clip(t, 2T, 8T), with T the path's length over the robot's top speed
  (the Jackal's 2 m/s in the challenge; our robot's own here) and t the time from the moment
  the robot has moved 0.1 m.

The committed conversion (`sim/data/barn.npz`, `BARN_FILE`) holds all 300 published worlds; it
was written by `qnav barn-convert FOLDER` from the commit named in its provenance.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.errors import ConfigError
from qnav.sim.layouts import Layouts, stack_layouts

F64 = NDArray[np.float64]

START_POSE = (-2.25, 3.0, 1.57)
"""The robot's start in BARN worlds (`run.py`, BARN branch): x, y in metres, heading in rad."""
GOAL_OFFSET_M = (0.0, 10.0)
"""The goal relative to the start (`run.py`'s GOAL_POSITION)."""
GOAL_RADIUS_M = 1.0
"""Success: the robot's centre within this of the goal (`run.py`)."""
TIME_LIMIT_S = 100.0
"""A run still going after this is a timeout (`run.py`)."""
MOVED_M = 0.1
"""The clock starts once the robot is this far from its start (`run.py`)."""
CELL_M = 0.15
"""BARN's grid pitch: the cylinders' diameter."""
PATH_ORIGIN_M = (-4.575, 5.075)
"""Where `path_coord_to_gazebo_coord` puts path cell (0, 0)."""

BARN_FILE = Path(__file__).parent / "data" / "barn.npz"
"""The committed conversion of the 300 published BARN worlds."""

_WORLD_NAME = re.compile(r"world_(\d+)\.world$")


def path_length_m(path_cells: NDArray[np.integer], start_xy: F64, goal_xy: F64) -> float:
    """Length of start -> path cells (mapped as `run.py` maps them) -> goal."""
    cells = np.asarray(path_cells, dtype=np.float64).reshape(-1, 2)
    points = np.vstack([start_xy, CELL_M * cells + np.array(PATH_ORIGIN_M), goal_xy])
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def metric(
    success: NDArray[np.bool_], time_s: F64, path_length_m: F64, top_speed_mps: float
) -> F64:
    """BARN's score per run: success x T / clip(t, 2T, 8T), T = path length / top speed."""
    optimal_s = np.asarray(path_length_m) / top_speed_mps
    clipped = np.clip(np.asarray(time_s, dtype=np.float64), 2 * optimal_s, 8 * optimal_s)
    return np.where(np.asarray(success), optimal_s / clipped, 0.0)


def read_world_cylinders(path: Path) -> tuple[F64, float]:
    """The static cylinders of one Gazebo world file: centres (K, 2) and their common radius.

    Models are read from the world's own `<model>` elements (not its `<state>` block); the
    ground plane and other models without a cylinder are skipped, and a model with any other
    solid (a box, a mesh) is refused, since this simulator would not see it.
    """
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as error:
        raise ConfigError(f"BARN world {path}: cannot be read ({error})") from None
    world = root.find("world")
    if world is None:
        raise ConfigError(f"BARN world {path}: no <world> element")
    centres, radii = [], set()
    for model in world.findall("model"):
        name = model.get("name", "?")
        shapes = model.findall("link/collision/geometry/*")
        if not shapes or all(shape.tag == "plane" for shape in shapes):
            continue
        if any(shape.tag != "cylinder" for shape in shapes) or len(shapes) != 1:
            kinds = ", ".join(sorted({shape.tag for shape in shapes}))
            raise ConfigError(f"BARN world {path}: model {name!r} has {kinds}; only cylinders")
        pose = (model.findtext("pose") or "0 0 0").split()
        radius = shapes[0].findtext("radius")
        if radius is None or len(pose) < 2:
            raise ConfigError(f"BARN world {path}: model {name!r} lacks a pose or a radius")
        centres.append((float(pose[0]), float(pose[1])))
        radii.add(round(float(radius), 6))
    if not centres:
        raise ConfigError(f"BARN world {path}: no cylinders")
    if len(radii) != 1:
        raise ConfigError(f"BARN world {path}: cylinders of several radii {sorted(radii)}")
    return np.array(centres, dtype=np.float64), radii.pop()


def world_numbers(folder: Path) -> list[int]:
    """The N of every `world_N.world` in a folder, ascending."""
    if not folder.is_dir():
        raise ConfigError(f"BARN folder {folder}: not a folder")
    numbers = sorted(
        int(match.group(1))
        for entry in folder.iterdir()
        if (match := _WORLD_NAME.search(entry.name)) is not None
    )
    if not numbers:
        raise ConfigError(f"BARN folder {folder}: no world_N.world files")
    return numbers


def read_barn_folder(folder: Path) -> Layouts:
    """Every `world_N.world` of a folder in BARN's format, with the paths beside them
    (`path_files/path_N.npy`; a world without one gets NaN as its path length)."""
    start = np.array(START_POSE)
    goal = start[:2] + np.array(GOAL_OFFSET_M)
    numbers = world_numbers(folder)
    cylinders, lengths, radii = [], [], set()
    for number in numbers:
        centres, radius = read_world_cylinders(folder / f"world_{number}.world")
        cylinders.append(centres)
        radii.add(radius)
        path_file = folder / "path_files" / f"path_{number}.npy"
        lengths.append(
            path_length_m(np.load(path_file), start[:2], goal) if path_file.is_file() else np.nan
        )
    if len(radii) != 1:
        raise ConfigError(f"BARN folder {folder}: cylinders of several radii {sorted(radii)}")
    count = len(numbers)
    return stack_layouts(
        name=str(folder),
        cylinders=cylinders,
        radius_m=radii.pop(),
        start_pose=np.tile(start, (count, 1)),
        goal_xy=np.tile(goal, (count, 1)),
        path_length_m=np.array(lengths),
        world_id=np.array(numbers, dtype=np.int64),
    )


def convert(
    folder: Path, out: Path, *, name: str, source: str, commit: str, licence: str
) -> Layouts:
    """Read a BARN-format folder and write its compact conversion, named `name`, with its
    provenance."""
    layouts = replace(read_barn_folder(folder), name=name)
    layouts.save(out, {"source": source, "commit": commit, "licence": licence})
    return layouts
