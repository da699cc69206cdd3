"""Where tracked obstacles may go: several motion hypotheses per obstacle, so that the forecast's
uncertainty grows with its horizon (`controller.lookahead`).

A person does not walk a straight line: the forecast's futures are random walks of each moving
obstacle's heading and speed from what the tracker measured, `turn_std_rad` and
`speed_std_mps` the spread of their change over one second (over t seconds, times the square
root of t). Future 0 is the straight line; an obstacle that stands (`tracker.moving_speed_mps`)
stands in every future. Obstacles bounce off the box that bounds the room's walls (the
reflection of a random walk is a random walk: `fold`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.lookahead import ObstacleFutures

F64 = NDArray[np.float64]


def fold(position: F64, low: F64 | float, high: F64 | float) -> F64:
    """Positions of a point that moved freely, reflected into [low, high] as often as it
    crossed either end (a specular bounce, however many)."""
    span = np.maximum(np.asarray(high) - np.asarray(low), 1e-9)
    offset = np.mod(position - low, 2 * span)
    return np.asarray(low + np.where(offset > span, 2 * span - offset, offset))


def walk_draws(
    random: np.random.Generator,
    *,
    futures: int,
    obstacles: int,
    steps: int,
    spread: tuple[float, float],
    period_s: float,
) -> F64:
    """(2, K, M, H) the random walks' steps of heading and speed of `obstacles` over `steps`
    periods in `futures` futures, drawn from `random` (future 0: none, the straight line)."""
    root = math.sqrt(period_s)
    scale = np.array([spread[0], spread[1]])[:, None, None, None] * root
    draws = random.standard_normal((2, futures, obstacles, steps)) * scale
    draws[:, 0] = 0.0
    return draws


def walked_futures(
    xy: F64, velocity: F64, radius_m: F64, draws: F64, *, period_s: float, box: tuple[F64, F64]
) -> ObstacleFutures:
    """N worlds' obstacles (N, M, 2) at `velocity` (N, M, 2) of `radius_m` (N, M) along the
    random walks `draws` (2, N, K, M, H) of heading and speed: their centres after each period
    in each future (H, N, K, M, 2), inside the `box` (low, high corners (2,)) less each radius;
    an obstacle that stands (no velocity) stands in every future."""
    speed0 = np.hypot(velocity[..., 0], velocity[..., 1])[:, None, :, None]  # (N, 1, M, 1)
    heading0 = np.arctan2(velocity[..., 1], velocity[..., 0])[:, None, :, None]
    heading = heading0 + np.cumsum(draws[0], axis=-1)  # (N, K, M, H)
    speed = np.where(speed0 > 0, np.maximum(speed0 + np.cumsum(draws[1], axis=-1), 0.0), 0.0)
    step = speed * period_s
    moved = np.stack([np.cos(heading) * step, np.sin(heading) * step], axis=-1)
    path = xy[:, None, :, None] + np.cumsum(moved, axis=3)  # (N, K, M, H, 2)
    reach = radius_m[:, None, :, None, None]
    centres = fold(path, box[0] + reach, box[1] - reach)
    return ObstacleFutures(np.ascontiguousarray(centres.transpose(3, 0, 1, 2, 4)), radius_m)


def random_futures(
    xy: F64,
    velocity: F64,
    radius_m: F64,
    *,
    steps: int,
    period_s: float,
    futures: int,
    spread: tuple[float, float],
    box: tuple[F64, F64],
    random: np.random.Generator,
) -> ObstacleFutures:
    """One car's obstacles (M, 2) in `futures` futures (`walk_draws`, `walked_futures`), as a
    world of one: (H, 1, K, M, 2)."""
    draws = walk_draws(
        random,
        futures=futures,
        obstacles=xy.shape[0],
        steps=steps,
        spread=spread,
        period_s=period_s,
    )
    return walked_futures(
        xy[None], velocity[None], radius_m[None], draws[:, None], period_s=period_s, box=box
    )


MEDIAN_OF_HALF_NORMAL = 0.6745
"""The median of |x| for x normal with standard deviation 1."""


def turn_from_misses(miss_m: F64, speed_mps: F64, lag_s: float) -> float:
    """The spread of a heading random walk (rad over one second) that explains straight-line
    forecasts of walkers at `speed_mps` (S,) missing by `miss_m` (S,) after `lag_s`: such a
    walk carries a walker about v sigma t^1.5 / sqrt(3) (standard deviation) off its line. From
    the median miss, so that a few misses against the wrong track (or a tracker's first,
    rough velocity) do not make straight walkers turn; 0 without misses."""
    if not miss_m.size:
        return 0.0
    spread = float(np.median(miss_m / speed_mps)) / MEDIAN_OF_HALF_NORMAL
    return math.sqrt(3.0) * spread / math.pow(lag_s, 1.5)


def informative_horizon_s(
    turn_std_rad: float, speed_mps: float, spread_m: float, bounds_s: tuple[float, float]
) -> float:
    """How long a walker at `speed_mps` whose heading walks with `turn_std_rad` stays within
    `spread_m` (root mean square) of its straight line, (sqrt(3) d / (v sigma))^(2/3), within
    `bounds_s` (the longest where it does not turn)."""
    if turn_std_rad * speed_mps <= 0:
        return bounds_s[1]
    horizon_s = math.pow(math.sqrt(3.0) * spread_m / (speed_mps * turn_std_rad), 2.0 / 3.0)
    return min(max(horizon_s, bounds_s[0]), bounds_s[1])
