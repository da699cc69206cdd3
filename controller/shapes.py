"""What each cluster of lidar returns is: the centre and the extent of an object of unknown size
and shape, from its points alone (`controller.perception` tracks them).

A real room holds cylinders of any radius, boxes, people's legs, furniture and walls that no map
holds. The tracker assumes none of them: a cluster is, in this order,

1. an arc: a circle of any radius up to `max_radius_m` fits its points within the range noise
   (`fit_arc`: the algebraic fit); the simulator's cylinders are found exactly;
2. arcs side by side: cut where the range peaks between them (a concave point: two convex
   objects merged in the scan) and each side an arc; or an arc and what shows of another
   that it mostly hides (`split_arcs`);
3. an object no wider than `piece_m`: its centre behind its points' middle by what a cylinder's
   near side would hide, its radius half its width across the line of sight or half its depth
   along it, whichever is larger (`extent`): robust to range noise, which moves points along
   the line of sight, not across it;
4. something wider (a wall or furniture the map lacks): pieces on a grid fixed in the room,
   `piece_m` a side, each the extent of its points (`grid_pieces`), so that what stands still
   is found in the same places scan after scan; nothing that wide moves in a room, so its
   tracks stand.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

MIN_ARC_POINTS = 5
"""Fewest points an arc is fitted to (fewer fix no radius)."""
MAX_SEARCH_POINTS = 60
"""Longest run searched for an arc and the rest (`arc_and_rest`: quadratic in its length)."""
SAME_ARC_M = 0.01
"""Returns beyond an arc that lie this near its circle are the same object (what a rotating
lidar's beams make of an obstacle that moves during them)."""
ARC_FLOOR_M = 0.001
"""Least root mean square residual an arc is allowed (where the lidar shows no noise)."""
HIDDEN_SHARE = math.pi / 4
"""How far a cylinder's centre lies behind the middle of its near side's points, in radii (the
mean depth of a half circle seen from afar: pi r / 4)."""


class Shape(NamedTuple):
    """One object found in a scan."""

    centre: F64
    """(2,) its centre in the room's frame."""
    radius_m: float
    """The radius of the circle round the centre that holds it."""
    beams: I64
    """The beams that found it."""
    wide: bool = False
    """A piece of something wider than a moving obstacle (`grid_pieces`): it stands."""
    run: int = 0
    """Which cluster of the scan it came from (shapes of one cluster are never joined)."""


def fit_arc(points: F64, sensor_xy: F64) -> tuple[F64, float, float]:
    """The circle (centre (2,), radius) through `points` (P, 2) seen from `sensor_xy`, by the
    algebraic fit (x^2 + y^2 + D x + E y + F = 0 in least squares, about the points' middle:
    exact for points on a circle); and the root mean square of the points' distances from it
    (inf where it fails: a centre in front of the points)."""
    middle = points.mean(axis=0)
    x, y = (points - middle).T
    design = np.column_stack([x, y, np.ones_like(x)])
    (d, e, f), *_ = np.linalg.lstsq(design, -(x * x + y * y), rcond=None)
    offset = np.array([-d / 2, -e / 2])
    radius_sq = float(offset @ offset - f)
    if radius_sq <= 0:
        return middle, 0.0, math.inf
    centre, radius = middle + offset, math.sqrt(radius_sq)
    residual = np.hypot(x - offset[0], y - offset[1]) - radius
    rms = float(np.sqrt(np.mean(residual * residual)))
    behind = float(offset @ (middle - sensor_xy)) > 0
    return centre, radius, rms if behind else math.inf


def fit_known_radius(points: F64, sensor_xy: F64, radius_m: float, iterations: int = 5) -> F64:
    """(2,) the centre of the circle of `radius_m` whose near side best fits `points` (P, 2)
    seen from `sensor_xy`: Gauss-Newton on the radial residuals, from the points' centroid
    pushed back by the radius along the line of sight. For an object partly seen (a few
    returns past another's edge) whose radius its track knows."""
    centroid = points.mean(axis=0)
    sight = centroid - sensor_xy
    centre = centroid + radius_m * sight / max(float(np.linalg.norm(sight)), 1e-9)
    if len(points) < 3:
        return np.asarray(centre)
    for _ in range(iterations):
        offset = points - centre
        distance = np.maximum(np.sqrt(np.einsum("ij,ij->i", offset, offset)), 1e-9)
        jacobian = -offset / distance[:, None]
        normal = jacobian.T @ jacobian  # 2 x 2: solved by hand, it is the hot loop
        gradient = jacobian.T @ (distance - radius_m)
        determinant = normal[0, 0] * normal[1, 1] - normal[0, 1] * normal[1, 0]
        if abs(determinant) < 1e-12:
            break
        step = np.array(
            [
                normal[1, 1] * gradient[0] - normal[0, 1] * gradient[1],
                normal[0, 0] * gradient[1] - normal[1, 0] * gradient[0],
            ]
        )
        centre = centre - step / determinant
    return np.asarray(centre)


def extent(points: F64, sensor_xy: F64, noise_m: float) -> tuple[F64, float, float]:
    """The centre (2,) and radius of an object of unknown shape from its points (P, 2) seen from
    `sensor_xy`: the centre behind the points' middle by `HIDDEN_SHARE` of half its width
    across the line of sight; the radius half that width, half its depth along the line of
    sight (less twice the range noise `noise_m`), or the farthest point from the centre (less
    the noise), whichever is largest."""
    middle = points.mean(axis=0)
    sight = middle - sensor_xy
    sight = sight / max(float(np.linalg.norm(sight)), 1e-9)
    across = (points - middle) @ np.array([-sight[1], sight[0]])
    along = (points - middle) @ sight
    width = float(np.ptp(across)) if len(points) > 1 else 0.0
    depth = max(float(np.ptp(along)) - 2 * noise_m, 0.0) if len(points) > 1 else 0.0
    centre = middle + HIDDEN_SHARE * (width / 2) * sight
    reach = float(np.max(np.linalg.norm(points - centre, axis=1))) - noise_m
    return np.asarray(centre), max(width / 2, depth / 2, reach), width


def arc_of(
    points: F64, sensor_xy: F64, noise_m: float, max_radius_m: float
) -> tuple[F64, float] | None:
    """The circle of an arc (`fit_arc`) whose radius is at most
    `max_radius_m` and whose points lie within the range noise of it (1.5 times `noise_m`, at
    least `ARC_FLOOR_M`); None where no such circle fits."""
    if len(points) < MIN_ARC_POINTS:
        return None
    centre, radius, rms = fit_arc(points, sensor_xy)
    if rms > max(1.5 * noise_m, ARC_FLOOR_M) or not 0.0 < radius <= max_radius_m:
        return None
    return centre, radius


def concave_cuts(ranges_m: F64, noise_m: float) -> list[int]:
    """Where a run of ranges (P,) peaks between two dips deeper than the noise (by at least
    twice `noise_m`, 2 cm or more): the indices that start the second of two convex objects the
    scan merged (the peak going with the side it is nearer to)."""
    depth = max(2 * noise_m, 0.02)
    cuts = []
    for k in range(2, len(ranges_m) - 2):
        peak = ranges_m[k]
        if peak == ranges_m[k - 2 : k + 3].max() and (
            peak - ranges_m[:k].min() > depth and peak - ranges_m[k + 1 :].min() > depth
        ):
            nearer_before = abs(peak - ranges_m[k - 1]) <= abs(peak - ranges_m[k + 1])
            cuts.append(k + 1 if nearer_before else k)
    return cuts


def arc_and_rest(
    run: I64, points: F64, sensor_xy: F64, noise_m: float, max_radius_m: float
) -> list[int]:
    """Where to cut `run` where no concave point shows (circles that overlap, one mostly hidden
    behind the other): after its longest first part that is an arc, or before its longest last
    part that is, whichever is longer (the rest is what shows of the other); none where
    neither is, or the whole is."""
    count = len(run)
    for length in range(count - 1, MIN_ARC_POINTS - 1, -1):
        for cut, part in ((length, run[:length]), (count - length, run[count - length :])):
            if arc_of(points[part], sensor_xy, noise_m, max_radius_m) is not None:
                return [cut]
    return []


def split_arcs(
    run: I64, points: F64, sensor_xy: F64, noise_m: float, max_radius_m: float
) -> list[Shape] | None:
    """`run` (beam indices) as arcs side by side, cut at its concave points; else an arc and
    what shows of another behind it (`arc_and_rest`); None where neither explains it."""
    ranges = np.linalg.norm(points[run] - sensor_xy, axis=1)
    cuts = concave_cuts(ranges, noise_m)
    if cuts:
        sides = np.split(run, cuts)
        arcs = [arc_of(points[side], sensor_xy, noise_m, max_radius_m) for side in sides]
        if all(arc is not None for arc in arcs):
            return [Shape(a[0], a[1], side) for a, side in zip(arcs, sides, strict=True) if a]
    if len(run) > MAX_SEARCH_POINTS:
        return None
    cut = arc_and_rest(run, points, sensor_xy, noise_m, max_radius_m)
    if not cut:
        return None
    sides = np.split(run, cut)
    fits = [arc_of(points[side], sensor_xy, noise_m, max_radius_m) for side in sides]
    arc = next(fit for fit in fits if fit is not None)
    rest = sides[1] if fits[0] is not None else sides[0]
    off = np.abs(np.linalg.norm(points[rest] - arc[0], axis=1) - arc[1])
    if off.max() <= max(3 * noise_m, SAME_ARC_M):  # a few stray returns of the same object
        return [Shape(arc[0], arc[1], run)]
    shapes = []
    for side, fit in zip(sides, fits, strict=True):
        centre, radius = fit if fit is not None else extent(points[side], sensor_xy, noise_m)[:2]
        shapes.append(Shape(centre, radius, side))
    return shapes


def grid_pieces(
    run: I64, points: F64, sensor_xy: F64, piece_m: float, noise_m: float
) -> list[Shape]:
    """`run`'s points grouped by the cell of a grid of `piece_m` fixed in the room, each group
    an object by its `extent` (its centre not pushed back: a wide thing's piece is a surface)."""
    cells = np.floor(points[run] / piece_m).astype(np.int64)
    _, group = np.unique(cells, axis=0, return_inverse=True)
    shapes = []
    for index in range(int(group.max()) + 1):
        beams = run[group.reshape(-1) == index]
        middle = points[beams].mean(axis=0)
        _, radius, _ = extent(points[beams], sensor_xy, noise_m)
        reach = float(np.max(np.linalg.norm(points[beams] - middle, axis=1)))
        shapes.append(Shape(np.asarray(middle), max(radius, reach), beams, wide=True))
    return shapes


def shapes_of(
    run: I64,
    points: F64,
    sensor_xy: F64,
    *,
    noise_m: float,
    max_radius_m: float,
    piece_m: float,
) -> list[Shape]:
    """The objects of one cluster (module docstring: arc, arcs, object, pieces)."""
    arc = arc_of(points[run], sensor_xy, noise_m, max_radius_m)
    if arc is not None:
        return [Shape(arc[0], arc[1], run)]
    arcs = split_arcs(run, points, sensor_xy, noise_m, max_radius_m)
    if arcs is not None:
        return arcs
    centre, radius, width = extent(points[run], sensor_xy, noise_m)
    if width <= piece_m:
        return [Shape(centre, radius, run)]
    return grid_pieces(run, points, sensor_xy, piece_m, noise_m)


def merge_close(shapes: list[Shape], points: F64, sensor_xy: F64, width_m: float) -> list[Shape]:
    """Neighbouring shapes of different clusters (in scan order, the last beside the first)
    that together are no wider than `width_m`, joined as one object by their `extent`: a
    person's two legs, the background seen between them."""
    merged: list[Shape] = []
    for shape in shapes:
        if merged and _together(merged[-1], shape, points, width_m):
            merged[-1] = _joined(merged[-1], shape, points, sensor_xy)
        else:
            merged.append(shape)
    if len(merged) > 1 and _together(merged[-1], merged[0], points, width_m):
        merged = [_joined(merged[-1], merged[0], points, sensor_xy), *merged[1:-1]]
    return merged


def _together(first: Shape, second: Shape, points: F64, width_m: float) -> bool:
    """Whether two shapes of different clusters together are no wider than `width_m` (neither
    a piece of a wide thing)."""
    if first.wide or second.wide or first.run == second.run:
        return False
    span = points[np.concatenate([first.beams, second.beams])]
    return float(np.max(np.linalg.norm(span - span.mean(axis=0), axis=1))) * 2 <= width_m


def _joined(first: Shape, second: Shape, points: F64, sensor_xy: F64) -> Shape:
    """Two shapes as one object, by the extent of their points."""
    beams = np.concatenate([first.beams, second.beams])
    centre, radius, _ = extent(points[beams], sensor_xy, 0.0)
    return Shape(centre, radius, beams, run=first.run)
