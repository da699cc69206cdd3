"""Worlds of BARN's family, generated: training and validation worlds that are not BARN's 300.

Every world has BARN's frame (`sim.barn`): a 4.5 m wide corridor of touching cylinders, a 30 x 30
field of 0.15 m cells starting 5.175 m ahead of the back wall, the start at (-2.25, 3) facing the
field and the goal 10 m ahead, beyond it. Field cell (r, c) holds a cylinder at
(-4.425 + 0.15 r, 5.175 + 0.15 c); rows 0 and 29 are the side walls.

Two families fill the field:

- "cave": BARN's own generator (Perille et al. 2020, `dperille/jackal-map-creation`), written
  anew: random fill at a rate in [0.15, 0.30], then 2-4 rounds of a cellular automaton (a cell
  with at least 5 filled neighbours fills, one with at most 1 empties; rows beyond the side walls
  count as filled);
- "rooms": two or three cross walls with doors, pockets open towards the start (dead ends that
  trap a robot heading straight for the goal), and stubs between doors.

As in BARN, a world is kept only if its C-space (cells with no cylinder within two cells, the
5 x 5 footprint of `c_space.py`) joins the field's near and far edges; interior cylinders (all
eight neighbours filled) are left out, since no ray reaches them. The reference path is the
shortest 8-connected C-space path from the start through the field to the goal.

The three splits draw from disjoint seed ranges, so validation and test worlds are never trained
on; training worlds also vary the start (x across the corridor, y, and heading).
"""

from __future__ import annotations

import heapq
import math
from functools import cache

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.errors import ConfigError
from qnav.sim import barn
from qnav.sim.layouts import Layouts, stack_layouts

F64 = NDArray[np.float64]
Grid = NDArray[np.bool_]

FAMILIES = ("cave", "rooms")
"""The generated families (`LayoutConfig.source`: one, or several joined by +)."""

FIELD_CELLS = 30
"""The field's side in cells (BARN's)."""
FIELD_ORIGIN_M = (-4.425, 5.175)
"""Centre of field cell (0, 0)."""
FOOTPRINT_CELLS = 2
"""C-space: the robot's centre keeps this many cells beyond its own from every filled cell."""
CAVE_FILL = (0.15, 0.30)
"""Initial fill rate range of the cave family (BARN's)."""
CAVE_SMOOTHING = (2, 4)
"""Cellular-automaton rounds of the cave family, inclusive (BARN's)."""
CORRIDOR_WALL_M = 5.0
"""Length of the containment side walls before the field (BARN's `contain_wall_length`)."""
TRAIN_START_X_M = (-3.6, -0.9)
"""Training worlds' start x range (BARN's start: -2.25)."""
TRAIN_START_Y_M = (1.5, 3.5)
"""Training worlds' start y range (BARN's: 3)."""
TRAIN_START_HEADING_RAD = math.pi / 4
"""Training worlds' start heading: BARN's +y, turned by up to this either way."""

_SPLIT_SEED = {"train": 0, "validation": 1_000_003, "test": 2_000_003}
"""First seed of each split; a world's seed is this plus its index."""
_ATTEMPTS = 1000
"""Draws per world before giving up (a cave at the densest fill is kept about one time in 5)."""


def cave_field(rng: np.random.Generator) -> Grid:
    """A cave field (rows r along x, columns c along y): BARN's cellular automaton."""
    fill = rng.uniform(*CAVE_FILL)
    rounds = int(rng.integers(CAVE_SMOOTHING[0], CAVE_SMOOTHING[1] + 1))
    grid = rng.random((FIELD_CELLS, FIELD_CELLS)) < fill
    grid[0, :] = grid[-1, :] = True
    for _ in range(rounds):
        # Beyond the side walls counts as filled; beyond the field's ends as empty.
        padded = np.pad(grid, 1, constant_values=False)
        padded[0, :] = padded[-1, :] = True
        neighbours = sum(
            padded[1 + dr : 1 + dr + FIELD_CELLS, 1 + dc : 1 + dc + FIELD_CELLS].astype(np.int64)
            for dr in (-1, 0, 1)
            for dc in (-1, 0, 1)
            if dr or dc
        )
        grid = np.where(neighbours >= 5, True, np.where(neighbours <= 1, False, grid))
    return np.asarray(grid, dtype=bool)


def rooms_field(rng: np.random.Generator) -> Grid:
    """A rooms field: cross walls with doors, dead-end pockets and stubs."""
    grid = np.zeros((FIELD_CELLS, FIELD_CELLS), dtype=bool)
    grid[0, :] = grid[-1, :] = True
    walls = int(rng.integers(2, 4))
    spacing = (FIELD_CELLS - 4) // walls
    for k in range(walls):
        c = 3 + k * spacing + int(rng.integers(0, max(1, spacing - 6)))
        grid[:, c] = True
        for _ in range(int(rng.integers(1, 3))):
            width = int(rng.integers(5, 9))
            start = int(rng.integers(1, FIELD_CELLS - 1 - width))
            grid[start : start + width, c] = False
        if rng.random() < 0.7:
            _add_pocket(grid, rng, c)
        if rng.random() < 0.5:
            r = int(rng.integers(3, FIELD_CELLS - 3))
            length = int(rng.integers(2, 6))
            grid[r, max(0, c - length) : c] = True
    return grid


def _add_pocket(grid: Grid, rng: np.random.Generator, wall_c: int) -> None:
    """A U open towards the start under the cross wall at column `wall_c`, closed at the wall."""
    width = int(rng.integers(6, 11))
    depth = int(rng.integers(4, 8))
    r0 = int(rng.integers(1, FIELD_CELLS - 1 - width))
    low = max(0, wall_c - depth)
    grid[r0, low:wall_c] = True
    grid[r0 + width, low:wall_c] = True
    grid[r0 : r0 + width + 1, wall_c] = True


def c_space(grid: Grid) -> Grid:
    """Cells where the robot's centre may be: no filled cell within FOOTPRINT_CELLS (the window
    clipped at the field's edges, as BARN's `c_space.py`)."""
    k = FOOTPRINT_CELLS
    padded = np.pad(grid, k, constant_values=False)
    blocked = np.zeros_like(grid)
    for dr in range(-k, k + 1):
        for dc in range(-k, k + 1):
            blocked |= padded[k + dr : k + dr + FIELD_CELLS, k + dc : k + dc + FIELD_CELLS]
    return ~blocked


def cell_xy(cells: NDArray[np.integer]) -> F64:
    """Centres (..., 2) of field cells (..., 2) = (r, c)."""
    return np.asarray(FIELD_ORIGIN_M) + barn.CELL_M * np.asarray(cells, dtype=np.float64)


def reference_path_m(free: Grid, start_xy: F64, goal_xy: F64) -> float:
    """Length of the shortest path start -> a free cell of column 0 -> 8-connected free cells
    (no squeezing between diagonal blocks) -> a free cell of the last column -> goal; inf if
    the field's ends are not joined."""
    n = FIELD_CELLS
    best = np.full((n, n), np.inf)
    queue: list[tuple[float, int, int]] = []
    for row in np.flatnonzero(free[:, 0]).tolist():
        best[row, 0] = float(np.linalg.norm(cell_xy(np.array([row, 0])) - start_xy))
        heapq.heappush(queue, (float(best[row, 0]), row, 0))
    total = math.inf
    while queue:
        cost, r, c = heapq.heappop(queue)
        if cost > best[r, c] or cost >= total:
            continue
        if c == n - 1:
            total = min(total, cost + float(np.linalg.norm(cell_xy(np.array([r, c])) - goal_xy)))
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if not (dr or dc) or not (0 <= rr < n and 0 <= cc < n) or not free[rr, cc]:
                    continue
                if dr and dc and not (free[r + dr, c] or free[r, c + dc]):
                    continue
                step = barn.CELL_M * (math.sqrt(2.0) if dr and dc else 1.0)
                if cost + step < best[rr, cc]:
                    best[rr, cc] = cost + step
                    heapq.heappush(queue, (cost + step, rr, cc))
    return total


def corridor_cylinders() -> F64:
    """The containment walls before the field: the back wall and the two side walls."""
    step = barn.CELL_M
    left, right = FIELD_ORIGIN_M[0], FIELD_ORIGIN_M[0] + step * (FIELD_CELLS - 1)
    back = [(x, step / 2) for x in np.arange(left, right + 1e-9, step)]
    side_y = np.arange(step / 2 + step, step / 2 + CORRIDOR_WALL_M + 1e-9, step)
    sides = [(x, y) for y in side_y for x in (left, right)]
    return np.array(back + sides, dtype=np.float64)


def field_cylinders(grid: Grid) -> F64:
    """Centres of the field's filled cells, without those whose eight neighbours are all filled
    (no ray reaches them; BARN's world writer leaves them out too)."""
    padded = np.pad(grid, 1, constant_values=False)
    enclosed = np.ones_like(grid)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                enclosed &= padded[1 + dr : 1 + dr + FIELD_CELLS, 1 + dc : 1 + dc + FIELD_CELLS]
    return cell_xy(np.argwhere(grid & ~enclosed))


def start_pose(rng: np.random.Generator, split: str) -> F64:
    """BARN's start, or for training a start drawn across the corridor."""
    pose = np.array(barn.START_POSE)
    if split == "train":
        pose[0] = rng.uniform(*TRAIN_START_X_M)
        pose[1] = rng.uniform(*TRAIN_START_Y_M)
        pose[2] += rng.uniform(-TRAIN_START_HEADING_RAD, TRAIN_START_HEADING_RAD)
    return pose


def generate_world(family: str, seed: int, split: str) -> tuple[F64, F64, float]:
    """One world of a family from its seed: cylinders (K, 2), start pose (3,), path length."""
    fields = {"cave": cave_field, "rooms": rooms_field}
    if family not in fields:
        raise ConfigError(f"layout family {family!r}: choose one of {', '.join(FAMILIES)}")
    rng = np.random.default_rng(seed)
    goal = np.array(barn.START_POSE[:2]) + np.array(barn.GOAL_OFFSET_M)
    for _ in range(_ATTEMPTS):
        grid = fields[family](rng)
        start = start_pose(rng, split)
        length = reference_path_m(c_space(grid), start[:2], goal)
        if math.isfinite(length):
            cylinders = np.vstack([corridor_cylinders(), field_cylinders(grid)])
            return cylinders, start, length
    raise ConfigError(f"layout family {family!r}: no passable world in {_ATTEMPTS} draws")


@cache
def generated_layouts(families: tuple[str, ...], split: str, worlds: int) -> Layouts:
    """`worlds` worlds of a split, the families taking turns (world i: family i mod F)."""
    if split not in _SPLIT_SEED:
        raise ConfigError(f"layout split {split!r}: choose one of {', '.join(_SPLIT_SEED)}")
    cylinders, starts, lengths = [], [], []
    for index in range(worlds):
        family = families[index % len(families)]
        centres, start, length = generate_world(family, _SPLIT_SEED[split] + index, split)
        cylinders.append(centres)
        starts.append(start)
        lengths.append(length)
    goal = np.array(barn.START_POSE[:2]) + np.array(barn.GOAL_OFFSET_M)
    return stack_layouts(
        name=f"{'+'.join(families)}/{split}",
        cylinders=cylinders,
        radius_m=barn.CELL_M / 2,
        start_pose=np.array(starts),
        goal_xy=np.tile(goal, (worlds, 1)),
        path_length_m=np.array(lengths),
        world_id=np.arange(worlds, dtype=np.int64),
    )
