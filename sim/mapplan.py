"""A planner given the map: cost-to-go over a fine grid of each static layout, and the action that
follows it (the teacher of imitation and the upper row of the BARN tables).

For each layout, the cost to reach the goal is computed once over a grid of `GRID_M` cells
(`cost_to_go`): a cell is blocked where the robot's disc, grown by `margin_m`, would touch a
cylinder; a step's cost is its length times 1 + `clearance_weight` x how far inside
`comfort_m` of a cylinder its cell lies (a costmap's inflation: keep to the middle of a gap
where there is room). At each decision the planner looks `lookahead_m` ahead in `DIRECTIONS`
directions and heads for the cheapest point: forward where the heading (corrected by the turn
still under way, for a robot with inertia) is within `aligned_rad` of it, else a turn towards it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import Action
from qnav.contracts.motion import InertiaDynamics
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


_WALL = 1.0e6
"""A step into a blocked cell in the line scans (`_line_scan`): far above any real cost."""


def relax(cost: F64, penalty: F64) -> F64:
    """The fixpoint of cost[i] = min(cost[i], cost[j] + |i - j| GRID_M penalty[i]) over the 8
    neighbours j (penalty inf: blocked). Each round scans every line both ways along both axes
    (exact for straight runs at once, by a running minimum) and then relaxes once towards all
    8 neighbours (the diagonals); a few rounds reach the fixpoint that single-cell sweeps reach
    only after one sweep per cell of the longest path."""
    blocked = ~np.isfinite(penalty)
    step = np.where(blocked, _WALL, GRID_M * np.where(blocked, 0.0, penalty))
    moves = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
    while True:
        before = cost
        for axis in (0, 1):
            for reverse in (False, True):
                cost = _line_scan(cost, step, axis, reverse)
        for dx, dy in moves:
            neighbour = _shifted(cost, dx, dy)
            cost = np.minimum(cost, neighbour + math.hypot(dx, dy) * step)
        cost[blocked | (cost >= _WALL / 2)] = np.inf
        # The running sums carry the walls' large steps, so rounding can lower a cost by about
        # 1e-7 m in every scan: stop when no cost falls by more than a micrometre.
        finite = np.isfinite(cost)
        if np.array_equal(finite, np.isfinite(before)) and np.allclose(
            cost[finite], before[finite], rtol=0.0, atol=1e-6
        ):
            return cost


def _line_scan(cost: F64, step: F64, axis: int, reverse: bool) -> F64:
    """cost[i] = min over j before i on its line of cost[j] + the steps from j to i: with S the
    running sum of the steps, min_j (cost[j] - S[j]) + S[i], a running minimum."""
    if reverse:
        return _line_scan(np.flip(cost, axis), np.flip(step, axis), axis, False)[
            (slice(None, None, -1),) if axis == 0 else (slice(None), slice(None, None, -1))
        ]
    total = np.cumsum(step, axis=axis)
    scanned: F64 = np.minimum.accumulate(cost - total, axis=axis) + total
    return np.minimum(cost, scanned)


def _shifted(values: F64, dx: int, dy: int) -> F64:
    """values[i + dx, j + dy] at [i, j] (inf beyond the edge)."""
    out = np.full_like(values, np.inf)
    nx, ny = values.shape
    out[max(0, -dx) : nx - max(0, dx), max(0, -dy) : ny - max(0, dy)] = values[
        max(0, dx) : nx - max(0, -dx), max(0, dy) : ny - max(0, -dy)
    ]
    return out


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
        self._lag_s = 0.0
        if isinstance(config.dynamics, InertiaDynamics):
            self._lag_s = config.dynamics.angular_time_constant_s

    def grid(self, layout: int) -> CostToGo:
        """The cost-to-go of a layout, computed at its first use."""
        if layout not in self._grids:
            self._grids[layout] = cost_to_go(
                self.layouts, layout, self.config.robot_radius_m, self.config.reach_m, self.settings
            )
        return self._grids[layout]

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        """No memory to reset."""

    def act(self, observation: Observation) -> NDArray[np.int64]:
        assert observation.layout is not None, "the map planner needs Observation.layout"
        pose = observation.pose
        actions = np.empty(pose.shape[0], dtype=np.int64)
        for row in range(pose.shape[0]):
            grid = self.grid(int(observation.layout[row]))
            ahead = pose[row, :2] + self.settings.lookahead_m * self._offsets
            costs = grid.at(ahead)
            best = int(np.argmin(costs))
            if not np.isfinite(costs[best]):
                actions[row] = Action.LEFT
                continue
            wanted = math.atan2(self._offsets[best, 1], self._offsets[best, 0])
            actions[row] = self.choose(pose[row, 2], wanted)
        return actions

    def choose(self, heading_rad: float, wanted_rad: float) -> int:
        """Forward when facing the wanted heading, else a turn towards it."""
        error = (wanted_rad - heading_rad + math.pi) % (2 * math.pi) - math.pi
        if abs(error) < self.settings.aligned_rad:
            return int(Action.FORWARD)
        return int(Action.LEFT if error > 0 else Action.RIGHT)
