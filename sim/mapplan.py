"""A planner given the map: cost-to-go over a fine grid of each static layout, and the action that
follows it (the teacher of imitation and the upper row of the BARN tables).

For each layout, the cost to reach the goal is computed once over a grid of `GRID_M` cells
(`cost_to_go`): a cell is blocked where the robot's disc, grown by `margin_m`, would touch a
cylinder; a step's cost is its length times 1 + `clearance_weight` x how far inside
`comfort_m` of a cylinder its cell lies (a costmap's inflation: keep to the middle of a gap
where there is room). At each decision the planner looks `lookahead_m` ahead in `DIRECTIONS`
directions and heads for the cheapest point: forward where the heading is within `aligned_rad`
of it (`open_aligned_rad` where no cylinder is within `open_m` of the robot's disc), else a turn
towards it.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import Action
from qnav.sim.config import WorldConfig
from qnav.sim.layouts import Layouts, layouts_of
from qnav.sim.world import Observation

F64 = NDArray[np.float64]

GRID_M = 0.05
"""Cell of the cost-to-go grid."""
BORDER_M = 1.0
"""The grid reaches this far beyond every cylinder, the start and the goal."""
DIRECTIONS = 48
"""Directions the planner looks in at each decision."""


@dataclass(frozen=True)
class MapPlanSettings:
    """How the planner given the map drives."""

    SECTION = "mapplan"

    margin_m: float = 0.03
    """Clearance beyond the robot's radius that the plan keeps from every cylinder."""
    comfort_m: float = 0.3
    """Within this of the plan's keep-out, steps cost more (the closer, the more)."""
    clearance_weight: float = 3.0
    """Extra cost per metre of a step at the keep-out's edge (0 at `comfort_m` from it)."""
    lookahead_m: float = 0.3
    """How far ahead the planner compares the cost-to-go to choose its heading."""
    aligned_rad: float = 0.25
    """Drive forward when the heading is within this of the chosen one, else turn."""
    open_aligned_rad: float = 0.5
    """... within this, where every cylinder is more than `open_m` beyond the robot's disc (in
    the open a rougher heading costs nothing, and a learner imitating the planner turns less
    often, and dithers less, between its turns)."""
    open_m: float = 0.7
    """Clearance beyond the robot's disc above which the robot counts as in the open."""


@dataclass(frozen=True, eq=False)
class CostToGo:
    """One layout's cost-to-go grid."""

    origin_xy: F64
    """(2,) centre of cell (0, 0)."""
    cost_m: F64
    """(X, Y) cost to the goal from each cell's centre; inf where blocked or cut off."""

    def at(self, xy: F64) -> F64:
        """Cost (...) at points (..., 2): the nearest cell's (inf outside the grid)."""
        index = np.rint((xy - self.origin_xy) / GRID_M).astype(np.int64)
        inside = (index >= 0).all(-1) & (index < np.array(self.cost_m.shape)).all(-1)
        clipped = np.clip(index, 0, np.array(self.cost_m.shape) - 1)
        cost: F64 = np.where(inside, self.cost_m[clipped[..., 0], clipped[..., 1]], np.inf)
        return cost


def nearest_surface_m(
    shape: tuple[int, ...], origin_xy: F64, centres: F64, radius_m: float, reach_m: float
) -> F64:
    """(X, Y) distance from each grid cell's centre to the nearest cylinder surface, exact
    within `reach_m` of a surface (each cylinder stamps the cells around it) and `reach_m`
    beyond."""
    span = math.ceil((reach_m + radius_m) / GRID_M)
    offsets = np.arange(-span, span + 1)
    window = np.stack(np.meshgrid(offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 2)
    home = np.rint((centres - origin_xy) / GRID_M).astype(np.int64)
    cells = (home[:, None, :] + window[None]).reshape(-1, 2)
    inside = (cells >= 0).all(-1) & (cells < np.array(shape)).all(-1)
    cells = cells[inside]
    owner = np.repeat(np.arange(centres.shape[0]), window.shape[0])[inside]
    gap = np.linalg.norm(origin_xy + GRID_M * cells - centres[owner], axis=1) - radius_m
    nearest = np.full(shape, reach_m)
    np.minimum.at(nearest, (cells[:, 0], cells[:, 1]), gap)
    return nearest


def cost_to_go(
    layouts: Layouts, index: int, robot_radius_m: float, reach_m: float, settings: MapPlanSettings
) -> CostToGo:
    """The cost-to-go grid of layout `index` (min-plus sweeps over 8 neighbours to a fixpoint)."""
    count = int(layouts.cylinder_count[index])
    centres = layouts.cylinder_xy[index, :count]
    goal = layouts.goal_xy[index]
    points = np.vstack([centres, layouts.start_pose[index, None, :2], goal[None]])
    low = points.min(axis=0) - BORDER_M
    high = points.max(axis=0) + BORDER_M
    shape = tuple(np.ceil((high - low) / GRID_M).astype(int) + 1)
    xs = low[0] + GRID_M * np.arange(shape[0])
    ys = low[1] + GRID_M * np.arange(shape[1])
    grid_xy = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    sight_m = robot_radius_m + settings.margin_m + settings.comfort_m + GRID_M
    gap = nearest_surface_m(shape, low, centres, layouts.cylinder_radius_m, sight_m)
    keep_out = gap - robot_radius_m - settings.margin_m
    blocked = keep_out < 0
    penalty = 1.0 + settings.clearance_weight * np.clip(1.0 - keep_out / settings.comfort_m, 0, 1)
    cost = np.full(shape, np.inf)
    in_goal = np.linalg.norm(grid_xy - goal, axis=1).reshape(shape) < 0.5 * reach_m
    cost[in_goal & ~blocked] = 0.0
    return CostToGo(origin_xy=low, cost_m=relax(cost, np.where(blocked, np.inf, penalty)))


def cache_folder() -> Path:
    """Where cost-to-go grids are kept between runs: $QNAV_CACHE/mapplan, else
    ~/.cache/qnav/mapplan (a grid takes a few tenths of a second to compute, and every run of
    a study plans in the same training worlds)."""
    root = os.environ.get("QNAV_CACHE") or Path.home() / ".cache" / "qnav"
    return Path(root) / "mapplan"


def cached_cost_to_go(
    layouts: Layouts, index: int, robot_radius_m: float, reach_m: float, settings: MapPlanSettings
) -> CostToGo:
    """`cost_to_go`, kept in `cache_folder()` under a hash of everything it depends on."""
    count = int(layouts.cylinder_count[index])
    key = hashlib.sha256()
    for part in (
        layouts.cylinder_xy[index, :count],
        layouts.start_pose[index],
        layouts.goal_xy[index],
        np.array([layouts.cylinder_radius_m, robot_radius_m, reach_m, GRID_M, BORDER_M]),
    ):
        key.update(np.ascontiguousarray(part, dtype=np.float64).tobytes())
    key.update(repr(settings).encode())
    path = cache_folder() / f"{key.hexdigest()[:32]}.npz"
    try:
        with np.load(path) as saved:
            return CostToGo(origin_xy=saved["origin_xy"], cost_m=saved["cost_m"].astype(np.float64))
    except (OSError, ValueError, KeyError):
        pass
    fresh = cost_to_go(layouts, index, robot_radius_m, reach_m, settings)
    # Kept and used in single precision both ways, so a cached grid plans as a fresh one.
    grid = CostToGo(fresh.origin_xy, fresh.cost_m.astype(np.float32).astype(np.float64))
    with contextlib.suppress(OSError):  # a read-only home only costs the time again
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.partial.npz")
        np.savez(partial, origin_xy=grid.origin_xy, cost_m=grid.cost_m.astype(np.float32))
        partial.replace(path)
    return grid


_WALL = 1.0e6
"""A step into a blocked cell in the line scans (`_line_scan`): far above any real cost."""


def relax(cost: F64, penalty: F64) -> F64:
    """The fixpoint of cost[i] = min(cost[i], cost[j] + |i - j| GRID_M penalty[i]) over the 8
    neighbours j (penalty inf: blocked). Each round scans every line of the grid both ways:
    rows, columns and both diagonals (a running minimum makes a whole straight run exact at
    once), so a few rounds reach the fixpoint that single-cell sweeps reach only after one
    sweep per cell of the longest path."""
    blocked = ~np.isfinite(penalty)
    step = np.where(blocked, _WALL, GRID_M * np.where(blocked, 0.0, penalty))
    skews = [_Skew(cost.shape, sign) for sign in (1, -1)]
    while True:
        before = cost
        for reverse in (False, True):
            for axis in (0, 1):
                cost = _line_scan(cost, step, axis, reverse)
            for skew in skews:  # along the diagonals: their steps are sqrt(2) cells long
                lines = _line_scan(skew(cost), skew(math.sqrt(2.0) * step, _WALL), 0, reverse)
                cost = np.minimum(cost, skew.back(lines))
        cost[blocked | (cost >= _WALL / 2)] = np.inf
        # The running sums carry the walls' large steps, so rounding can lower a cost by about
        # 1e-7 m in every scan: stop when no cost falls by more than a micrometre.
        finite = np.isfinite(cost)
        if np.array_equal(finite, np.isfinite(before)) and np.allclose(
            cost[finite], before[finite], rtol=0.0, atol=1e-6
        ):
            return cost


class _Skew:
    """Shears an (X, Y) grid so that its diagonals (sign 1: i and j rising together; -1: j
    falling as i rises) become the columns of an (X, X + Y - 1) one, padded outside the grid."""

    def __init__(self, shape: tuple[int, ...], sign: int) -> None:
        rows, cols = shape
        i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        self.rows, self.width = i, (j - sign * i + (rows - 1 if sign > 0 else 0))
        self.shape = (rows, rows + cols - 1)

    def __call__(self, grid: F64, pad: float = np.inf) -> F64:
        sheared = np.full(self.shape, pad)
        sheared[self.rows, self.width] = grid
        return sheared

    def back(self, sheared: F64) -> F64:
        grid: F64 = sheared[self.rows, self.width]
        return grid


def _line_scan(cost: F64, step: F64, axis: int, reverse: bool) -> F64:
    """cost[i] = min over j before i on its line of cost[j] + the steps from j to i: with S the
    running sum of the steps, min_j (cost[j] - S[j]) + S[i], a running minimum."""
    if reverse:
        flipped = _line_scan(np.flip(cost, axis), np.flip(step, axis), axis, False)
        return np.flip(flipped, axis)
    total = np.cumsum(step, axis=axis)
    scanned: F64 = np.minimum.accumulate(cost - total, axis=axis) + total
    return np.minimum(cost, scanned)


class MapPlanner:
    """An agent given the map of every layout (`Observation.layout`): follows the cost-to-go."""

    def __init__(self, config: WorldConfig, settings: MapPlanSettings | None = None) -> None:
        layouts = layouts_of(config.layout)
        if layouts is None:
            raise ValueError("the map planner needs a world of static layouts (layout.source)")
        self.layouts = layouts
        self.config = config
        self.settings = settings or MapPlanSettings()
        self._grids: dict[int, CostToGo] = {}
        angles = np.linspace(0.0, 2 * math.pi, DIRECTIONS, endpoint=False)
        self._offsets = np.stack([np.cos(angles), np.sin(angles)], axis=-1)

    def grid(self, layout: int) -> CostToGo:
        """The cost-to-go of a layout: computed at its first use, or read from the cache."""
        if layout not in self._grids:
            self._grids[layout] = cached_cost_to_go(
                self.layouts, layout, self.config.robot_radius_m, self.config.reach_m, self.settings
            )
        return self._grids[layout]

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """No memory to reset."""

    def act(self, observation: Observation) -> NDArray[np.int64]:
        assert observation.layout is not None, "the map planner needs Observation.layout"
        return self.act_at(observation.pose, observation.layout)

    def act_at(self, pose: F64, layout: NDArray[np.int64]) -> NDArray[np.int64]:
        """The action in each world from its pose (N, 3) in its layout (N,)."""
        actions = np.empty(pose.shape[0], dtype=np.int64)
        centres = self.layouts.cylinders_of(layout)
        gap = np.sqrt(((centres - pose[:, None, :2]) ** 2).sum(-1).min(axis=1))
        room = gap - self.layouts.cylinder_radius_m - self.config.robot_radius_m
        open_ = room > self.settings.open_m
        for row in range(pose.shape[0]):
            grid = self.grid(int(layout[row]))
            ahead = pose[row, :2] + self.settings.lookahead_m * self._offsets
            costs = grid.at(ahead)
            best = int(np.argmin(costs))
            if not np.isfinite(costs[best]):
                actions[row] = Action.LEFT
                continue
            wanted = math.atan2(self._offsets[best, 1], self._offsets[best, 0])
            actions[row] = self.choose(pose[row, 2], wanted, bool(open_[row]))
        return actions

    def choose(self, heading_rad: float, wanted_rad: float, in_open: bool = False) -> int:
        """Forward when facing the wanted heading, else a turn towards it."""
        error = (wanted_rad - heading_rad + math.pi) % (2 * math.pi) - math.pi
        aligned = self.settings.open_aligned_rad if in_open else self.settings.aligned_rad
        if abs(error) < aligned:
            return int(Action.FORWARD)
        return int(Action.LEFT if error > 0 else Action.RIGHT)
