"""The planner given the map: its cost-to-go is the shortest 8-connected path's."""

import heapq
import math

import numpy as np

from qnav.sim.mapplan import GRID_M, relax


def dijkstra(cost: np.ndarray, penalty: np.ndarray) -> np.ndarray:
    best = cost.copy()
    queue = [(float(v), i, j) for (i, j), v in np.ndenumerate(cost) if np.isfinite(v)]
    heapq.heapify(queue)
    rows, cols = cost.shape
    while queue:
        value, i, j = heapq.heappop(queue)
        if value > best[i, j]:
            continue
        # A step from (a, b) to its neighbour (i, j) costs its length times penalty[a, b].
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                a, b = i + di, j + dj
                if not (di or dj) or not (0 <= a < rows and 0 <= b < cols):
                    continue
                if not np.isfinite(penalty[a, b]):
                    continue
                candidate = value + GRID_M * math.hypot(di, dj) * penalty[a, b]
                if candidate < best[a, b] - 1e-12:
                    best[a, b] = candidate
                    heapq.heappush(queue, (candidate, a, b))
    return best


def test_relaxation_finds_the_shortest_paths_around_walls() -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        penalty = 1.0 + 3.0 * rng.random((23, 31))
        penalty[rng.random(penalty.shape) < 0.25] = np.inf
        cost = np.full(penalty.shape, np.inf)
        cost[0, 0] = 0.0
        penalty[0, 0] = 1.0
        expected = dijkstra(cost, penalty)
        np.testing.assert_allclose(relax(cost, penalty), expected, atol=1e-6)
