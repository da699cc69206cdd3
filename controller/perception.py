"""Moving obstacles from a lidar and a motion-capture pose: a small tracker, numpy only.

The paper's network is asked to find moving obstacles in raw ranges; measured, it does not
(docs/learner.md, "Why: perception and the doom function's appetite for data"). Indoors the car
knows its pose (motion capture) and the room's walls, which makes the job classical and cheap:

1. every return becomes a point in the room's frame (`scan_points`), placed from the car's pose
   when it was taken (`beam_poses`: a rotating lidar's beams leave over its turn);
2. returns on a known wall are the wall (`off_the_walls`, within a band that widens with the
   range noise the walls' own returns show: `wall_noise`); the rest is grouped into runs of
   neighbouring beams (`clusters`), and runs that together are as narrow as a person's two legs
   are joined (`shapes.merge_close`);
3. each cluster is an object of unknown size and shape, its centre and radius from its points
   alone (`controller.shapes`: an arc of any radius, arcs side by side, an object's extent, or
   pieces of something wide on a grid fixed in the room);
4. detections join tracks by nearest prediction within a gate; a track's velocity is the slope
   of a straight-line fit to its recent centres, over the longest recent stretch that is
   straight within the noise (an obstacle that bounced off a wall starts a new stretch)
   (`fit_velocity`); a track slower than `moving_speed_mps` stands (static things told from
   moving ones).

`ObstacleTracker` holds one world's tracks; the functions are pure. The car's own velocity
comes from its last two poses (`ego_velocity`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import distance_to_segments
from qnav.contracts.settings import check_range
from qnav.controller.shapes import (
    MIN_ARC_POINTS,
    Shape,
    fit_known_radius,
    merge_close,
    shapes_of,
)

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class TrackerSettings:
    """How the tracker reads a scan and keeps its tracks."""

    SECTION = "tracker"

    max_radius_m: float = 0.6
    """Largest radius of an arc the tracker fits to a cluster (a round obstacle); a cluster no
    arc fits is taken by its extent."""
    piece_m: float = 1.0
    """A cluster wider than this that no arcs explain (a wall or furniture the map lacks) is
    cut into pieces of this size on a grid fixed in the room, so that it stands still."""
    legs_m: float = 0.5
    """Neighbouring clusters that together are no wider than this are one object (a person's
    two legs, the background between them)."""
    moving_speed_mps: float = 0.2
    """A track slower than this is forecast standing where it is (static things, and people
    who stopped)."""
    wall_band_m: float = 0.1
    """Returns within this distance of a known wall belong to the wall; the band widens to
    3.5 times the range noise the walls' own returns show (`wall_noise`)."""
    min_returns: int = 1
    """Fewest neighbouring returns that make an obstacle; one found by a single return counts
    once it is found again in the next scans (a lone stray return does not; a thin pole far
    away, a few centimetres wide, returns one)."""
    cluster_gap_m: float = 0.3
    """Neighbouring returns farther apart than this belong to different objects."""
    gate_m: float = 0.3
    """A detection farther than this from every track's prediction starts a new track."""
    max_obstacle_speed_mps: float = 2.0
    """Fastest obstacle expected: a track seen once (no velocity yet) reaches this far."""
    velocity_frames: int = 5
    """Most recent centres a velocity is fitted to, one per scan tracked (5: 0.8 s of a 5 Hz
    lidar; with a faster lidar raise it in proportion to keep the span)."""
    straight_tolerance_m: float = 0.03
    """Largest residual of a centre from the fitted line for a stretch to count as straight
    (at least the range noise the walls show)."""
    coast_frames: int = 3
    """Scans a track is kept (moved by its velocity) without a detection (3: 0.6 s at 5 Hz;
    scale it with the lidar's rate as `velocity_frames`)."""

    def __post_init__(self) -> None:
        check_range(self, "max_radius_m", self.max_radius_m, 0.0, 100.0, exclusive_low=True)
        check_range(self, "piece_m", self.piece_m, 0.0, 100.0, exclusive_low=True)
        check_range(self, "legs_m", self.legs_m, 0.0, 10.0)
        check_range(self, "moving_speed_mps", self.moving_speed_mps, 0.0, 100.0)
        check_range(self, "wall_band_m", self.wall_band_m, 0.0, 10.0)
        check_range(self, "min_returns", self.min_returns, 1, 100_000)
        check_range(self, "cluster_gap_m", self.cluster_gap_m, 0.0, 10.0, exclusive_low=True)
        check_range(self, "gate_m", self.gate_m, 0.0, 100.0, exclusive_low=True)
        check_range(self, "max_obstacle_speed_mps", self.max_obstacle_speed_mps, 0.0, 100.0)
        check_range(self, "velocity_frames", self.velocity_frames, 2, 1000)
        check_range(self, "straight_tolerance_m", self.straight_tolerance_m, 0.0, 10.0)
        check_range(self, "coast_frames", self.coast_frames, 0, 1000)


def box_walls(size_m: float) -> F64:
    """(4, 4) wall segments (x0, y0, x1, y1) of a square room [0, size_m]^2."""
    s = size_m
    return np.array([[0, 0, s, 0], [s, 0, s, s], [s, s, 0, s], [0, s, 0, 0]], dtype=np.float64)


def scan_points(scan_m: NDArray[np.floating], pose: F64, beam_angles_rad: F64) -> F64:
    """(B, 2) each return's position in the room's frame (nan where there is no return), seen
    from `pose`: the scan's one pose (3,), or each beam's own (B, 3) (`beam_poses`)."""
    ranges = np.where(np.isfinite(scan_m), scan_m, np.nan).astype(np.float64)
    angle = pose[..., 2] + beam_angles_rad
    return np.stack(
        [pose[..., 0] + ranges * np.cos(angle), pose[..., 1] + ranges * np.sin(angle)], axis=1
    )


def beam_poses(poses: F64, times_s: F64, beam_times_s: F64) -> F64:
    """(B, 3) the car's pose when each beam was taken, on the line through its last two poses
    (2, 3) taken at `times_s` (2,): a rotating lidar's beams leave over its turn, while the car
    moves, so each return is placed from where the car was at its own time."""
    rate = (poses[1] - poses[0]) / (times_s[1] - times_s[0])
    rate[2] = math.remainder(float(poses[1, 2] - poses[0, 2]), math.tau) / (times_s[1] - times_s[0])
    return np.asarray(poses[1] + (beam_times_s - times_s[1])[:, None] * rate)


def distance_to_walls(points: F64, walls: F64) -> F64:
    """(P,) each point's distance to the nearest wall segment (x0, y0, x1, y1)."""
    return distance_to_segments(points, walls[:, :2], walls[:, 2:])


def off_the_walls(points: F64, walls: F64, band_m: float) -> NDArray[np.bool_]:
    """(B,) True for returns that are not on a known wall (and are returns at all)."""
    valid = np.all(np.isfinite(points), axis=1)
    keep: NDArray[np.bool_] = valid.copy()
    keep[valid] = distance_to_walls(points[valid], walls) > band_m
    return keep


def clusters(points: F64, keep: NDArray[np.bool_], gap_m: float) -> list[NDArray[np.int64]]:
    """Runs of neighbouring kept beams whose consecutive points are within `gap_m`, as beam
    indices; the scan is circular, so a run may wrap past the last beam."""
    beams = np.flatnonzero(keep)
    if beams.size == 0:
        return []
    step = np.linalg.norm(np.diff(points[beams], axis=0), axis=1)
    breaks = (np.diff(beams) != 1) | (step > gap_m)
    runs = np.split(beams, np.flatnonzero(breaks) + 1)
    count = keep.size
    wraps = (
        len(runs) > 1
        and runs[0][0] == 0
        and runs[-1][-1] == count - 1
        and np.linalg.norm(points[0] - points[count - 1]) <= gap_m
    )
    if wraps:
        runs = [np.concatenate([runs[-1], runs[0]]), *runs[1:-1]]
    return runs


PARTLY_SEEN = 0.7
"""A detection of fewer points than an arc needs and narrower than this share of its track's
radius is a part of the object its track knows (`ObstacleTracker.update`)."""
MIN_KNOWN_POINTS = 3
"""Fewest points that place a partly seen object by its track's radius."""
NOISE_NEAR_WALL_M = 0.3
"""Returns within this of a known wall tell the range noise (`wall_noise`)."""
NOISE_MEMORY = 0.2
"""Weight of each scan's noise estimate in the running one."""
STATIC_CELL_M = 0.15
"""Side of the cells of the grid fixed in the room where evidence of standing things gathers
(`StaticGrid`): about a thin pole's diameter, a third of a person's width."""
STATIC_EVIDENCE = 8.0
"""Evidence (scans that hit a cell, each decayed by `STATIC_MEMORY` a scan since) from which the
cell's returns are of something that stands: a thing in view stands from its tenth scan (1.8 s
at 5 Hz); an obstacle of 0.2 m radius crossing the view at 0.5 m/s hits a cell for about 5."""
STATIC_MEMORY = 0.98
"""Share of a cell's evidence kept from one scan to the next (a thing out of sight for 35 scans,
7 s at 5 Hz, keeps half of it)."""


def wall_noise(points: F64, walls: F64, sensor_xy: F64 | None = None) -> float | None:
    """The range noise the walls' returns show: a robust standard deviation (1.4826 times the
    median absolute distance) of the returns within `NOISE_NEAR_WALL_M` of a known wall; None
    with fewer than 20 such returns. Seen from `sensor_xy`, only the returns beyond their
    nearest wall count (half a wall's noisy returns fall there, at the same distances as the
    other half; nothing else does), so that clutter standing near a wall is not taken for
    noise; None with fewer than 10 of them."""
    valid = np.all(np.isfinite(points), axis=1)
    if sensor_xy is None:
        distance = distance_to_walls(points[valid], walls)
        near = distance[distance < NOISE_NEAR_WALL_M]
        return float(1.4826 * np.median(near)) if near.size >= 20 else None
    start, along = walls[:, :2], walls[:, 2:] - walls[:, :2]
    offset = points[valid][:, None] - start[None]  # (P, W, 2)
    t = np.clip(np.sum(offset * along, axis=2) / np.sum(along * along, axis=1), 0.0, 1.0)
    distance = np.linalg.norm(offset - t[..., None] * along, axis=2)
    nearest = distance.argmin(axis=1)
    rows = np.arange(len(nearest))
    wall, point, sensor = along[nearest], offset[rows, nearest], sensor_xy - start[nearest]
    side = wall[:, 0] * point[:, 1] - wall[:, 1] * point[:, 0]
    sensor_side = wall[:, 0] * sensor[:, 1] - wall[:, 1] * sensor[:, 0]
    beyond = (distance[rows, nearest] < NOISE_NEAR_WALL_M) & (side * sensor_side < 0)
    if beyond.sum() < 10:
        return None
    return float(1.4826 * np.median(distance[rows, nearest][beyond]))


def bounce_mirrors(walls: F64, radius_m: float) -> F64:
    """(2W, 3) lines (unit normal x, y, offset c: n . p = c) where a centre of an obstacle of
    `radius_m` touches each wall, on either side of it: the mirrors its bounces reflect in."""
    start, end = walls[:, :2], walls[:, 2:]
    along = (end - start) / np.linalg.norm(end - start, axis=1, keepdims=True)
    normal = np.stack([-along[:, 1], along[:, 0]], axis=1)
    offset = np.sum(normal * start, axis=1)
    return np.concatenate(
        [np.column_stack([normal, offset + radius_m]), np.column_stack([normal, offset - radius_m])]
    )


class StaticGrid:
    """Evidence, cell by cell of a grid fixed in the room (the walls' bounding box, cells of
    `STATIC_CELL_M`), of what stands there: every scan adds one to each cell its returns hit,
    and every cell keeps `STATIC_MEMORY` of its evidence from one scan to the next. A return in
    a cell whose evidence from the earlier scans reaches `STATIC_EVIDENCE` is of something that
    stands: clutter the map lacks, which a moving obstacle passes, or a person who stopped.
    (The car's pose comes from motion capture, so a standing thing's returns fall in the same
    cells scan after scan however the car moves; a moving obstacle's, in each for a few.)"""

    def __init__(self, walls: F64) -> None:
        corners = walls.reshape(-1, 2)
        self.low = corners.min(axis=0) - STATIC_CELL_M
        size = np.ceil((corners.max(axis=0) + STATIC_CELL_M - self.low) / STATIC_CELL_M)
        self.evidence = np.zeros(size.astype(np.int64))

    def _cells(self, points: F64, keep: NDArray[np.bool_]) -> tuple[NDArray[np.int64], ...]:
        """The beams of `keep` whose points lie on the grid, and their cells' (row, column)."""
        cell = np.floor((points - self.low) / STATIC_CELL_M)
        inside = keep & np.all((cell >= 0) & (cell < self.evidence.shape), axis=1)
        beams = np.flatnonzero(inside)
        return beams, cell[beams, 0].astype(np.int64), cell[beams, 1].astype(np.int64)

    def standing(self, points: F64, keep: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """(B,) True for the returns of `keep` in cells where things stand."""
        beams, row, column = self._cells(points, keep)
        standing = np.zeros(len(points), dtype=bool)
        standing[beams] = self.evidence[row, column] >= STATIC_EVIDENCE
        return standing

    def add(self, points: F64, keep: NDArray[np.bool_]) -> None:
        """Take in one scan's returns of `keep` (after the older evidence decayed)."""
        self.evidence *= STATIC_MEMORY
        _, row, column = self._cells(points, keep)
        hit = np.zeros(self.evidence.shape, dtype=bool)
        hit[row, column] = True
        self.evidence[hit] += 1.0


def _straight_slope(times_s: F64, centres: F64, tolerance_m: float) -> F64 | None:
    """The velocity of a straight-line fit to the centres, or None if one strays beyond
    `tolerance_m` from it."""
    t = times_s - times_s[-1]
    design = np.stack([np.ones_like(t), t], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, centres, rcond=None)
    residual = centres - design @ coefficients
    if len(t) > 2 and np.max(np.linalg.norm(residual, axis=1)) > tolerance_m:
        return None
    return np.asarray(coefficients[1])


def fit_velocity(times_s: F64, centres: F64, tolerance_m: float, mirrors: F64 | None = None) -> F64:
    """(2,) velocity of the latest centres: the slope of a straight-line fit to all of them;
    else, if one bounce off a wall explains them (the centres after it reflected in one of
    `mirrors` continue the line before it), that line's slope reflected back; else the slope
    of the longest recent stretch that is straight (at least the last two). Zero with fewer
    than two centres."""
    if len(times_s) < 2:
        return np.zeros(2)
    slope = _straight_slope(times_s, centres, tolerance_m)
    if slope is not None:
        return slope
    for split in range(len(times_s) - 1, 0, -1):  # the latest bounce first
        for mirror in mirrors if mirrors is not None else np.zeros((0, 3)):
            normal, offset = mirror[:2], mirror[2]
            unfolded = centres.copy()
            after = centres[split:]
            unfolded[split:] = after - 2 * (after @ normal - offset)[:, None] * normal
            slope = _straight_slope(times_s, unfolded, tolerance_m)
            if slope is not None:
                return np.asarray(slope - 2 * (slope @ normal) * normal)
    for first in range(1, len(times_s) - 1):  # longest stretch first
        slope = _straight_slope(times_s[first:], centres[first:], tolerance_m)
        if slope is not None:
            return slope
    return np.asarray(_straight_slope(times_s[-2:], centres[-2:], tolerance_m))


def ego_velocity(previous_pose: F64, pose: F64, period_s: float) -> F64:
    """(2,) forward speed (m/s) and turn rate (rad/s) over the last period, from two poses."""
    turn = math.remainder(float(pose[2] - previous_pose[2]), 2 * math.pi)
    middle = previous_pose[2] + turn / 2
    moved = pose[:2] - previous_pose[:2]
    forward = moved[0] * math.cos(middle) + moved[1] * math.sin(middle)
    return np.array([forward / period_s, turn / period_s])


def own_velocity(poses: F64, intervals_s: F64) -> F64:
    """(2,) forward speed and turn rate now, from the last two or three poses (P, 3) and the
    P - 1 intervals between them: the mean over the last interval, extrapolated to its end by
    half the change since the interval before (the mean lags by half an interval). Zero from
    a single pose."""
    if len(poses) < 2:
        return np.zeros(2)
    velocity = ego_velocity(poses[-2], poses[-1], float(intervals_s[-1]))
    if len(poses) > 2:
        velocity += (velocity - ego_velocity(poses[-3], poses[-2], float(intervals_s[-2]))) / 2
    return velocity


def seen_once(
    centres: F64, seen_s: F64, radii_m: F64, span_s: float, speed_mps: float
) -> NDArray[np.int64]:
    """Indices of the detections (D, 2) to keep from a rotating lidar's scan, whose beams at the
    seam (its first and last) may see one obstacle twice, a turn apart: of two detections that
    may be one obstacle (closer than their radii (D,) together and what `speed_mps` covers in
    the time between them) and were seen more than half the scan's span (`span_s`) apart, the
    later (obstacles that overlap are seen at once, and both are kept)."""
    kept: list[int] = []
    for index in np.argsort(-seen_s, kind="stable"):
        twice = any(
            seen_s[other] - seen_s[index] > span_s / 2
            and np.linalg.norm(centres[index] - centres[other])
            < radii_m[index] + radii_m[other] + speed_mps * (seen_s[other] - seen_s[index])
            for other in kept
        )
        if not twice:
            kept.append(int(index))
    return np.array(sorted(kept), dtype=np.int64)


def _sensor_xy(pose: F64, beams: NDArray[np.int64]) -> F64:
    """Where the lidar was while it took `beams`: the scan's pose, or their poses' mean."""
    return pose[:2] if pose.ndim == 1 else np.asarray(pose[beams, :2].mean(axis=0))


class Tracks(NamedTuple):
    """What the tracker believes now, in the room's frame."""

    xy_m: F64
    """(K, 2) obstacle centres."""
    velocity_mps: F64
    """(K, 2) obstacle velocities (zero for those that stand)."""
    radius_m: F64
    """(K,) each obstacle's radius, from its points."""


@dataclass
class _Track:
    times_s: deque[float]
    centres: deque[F64]
    radii: deque[float]
    velocity: F64 = field(default_factory=lambda: np.zeros(2))
    missed: int = 0
    hits: int = 1
    single: bool = False
    """Found by one return each time so far (a stray return, or a thin pole far away)."""
    wide: bool = False
    """Found as a piece of something wide (`shapes.grid_pieces`) at least once: it stands."""
    static: bool = False
    """Found where things stand (`StaticGrid`): it stands, and takes only detections found
    there (a moving obstacle passing it is another track)."""

    @property
    def radius_m(self) -> float:
        """The median of its recent radii."""
        ordered = sorted(self.radii)
        return ordered[len(ordered) // 2]

    def predicted(self, time_s: float) -> F64:
        return np.asarray(self.centres[-1] + self.velocity * (time_s - self.times_s[-1]))


class ObstacleTracker:
    """One room's obstacle tracks, updated with each scan and the pose it was taken from."""

    def __init__(self, settings: TrackerSettings, walls: F64, beam_angles_rad: F64) -> None:
        self.settings = settings
        self.walls = walls
        self.beam_angles_rad = beam_angles_rad
        self.noise_m = 0.0
        """The range noise the walls' returns have shown so far (`wall_noise`, averaged)."""
        self._tracks: list[_Track] = []
        self._time_s = 0.0
        self._mirror_cache: dict[float, F64] = {}
        self.grid = StaticGrid(walls)
        """Where things stand, from the scans so far."""

    def detect(self, scan_m: NDArray[np.floating], pose: F64) -> list[Shape]:
        """The objects found in one scan seen from `pose` (as `scan_points`)."""
        return self._detect(scan_points(scan_m, pose, self.beam_angles_rad), pose)[0]

    def _detect(self, points: F64, pose: F64) -> tuple[list[Shape], NDArray[np.bool_]]:
        """`detect` on the scan's points in the room's frame (B, 2), and which of the objects
        were found where things stand."""
        s = self.settings
        sensor_xy = _sensor_xy(pose, np.arange(len(points)))
        measured = wall_noise(points, self.walls, sensor_xy)
        if measured is not None:
            weight = NOISE_MEMORY if self.noise_m else 1.0
            self.noise_m += weight * (measured - self.noise_m)
        band = max(s.wall_band_m, 3.5 * self.noise_m)
        keep = off_the_walls(points, self.walls, band)
        standing = self.grid.standing(points, keep)
        self.grid.add(points, keep)
        moving = self._objects(points, pose, sensor_xy, keep & ~standing, 0)
        static = self._objects(points, pose, sensor_xy, standing, len(points))
        return moving + static, np.arange(len(moving) + len(static)) >= len(moving)

    def _objects(
        self, points: F64, pose: F64, sensor_xy: F64, keep: NDArray[np.bool_], first_run: int
    ) -> list[Shape]:
        """The objects the returns of `keep` make (their clusters numbered from `first_run`),
        the scan seen from `sensor_xy`."""
        s = self.settings
        gap = max(s.cluster_gap_m, 4.0 * self.noise_m)
        found = []
        for index, run in enumerate(clusters(points, keep, gap)):
            shapes = shapes_of(
                run,
                points,
                _sensor_xy(pose, run),
                noise_m=self.noise_m,
                max_radius_m=s.max_radius_m,
                piece_m=s.piece_m,
            )
            found += [shape._replace(run=first_run + index) for shape in shapes]
        found = merge_close(found, points, sensor_xy, s.legs_m)
        return [shape for shape in found if len(shape.beams) >= s.min_returns]

    def update(
        self,
        time_s: float,
        scan_m: NDArray[np.floating],
        pose: F64,
        beam_times_s: F64 | None = None,
    ) -> Tracks:
        """Take in a scan taken at `time_s` from `pose`, or beam by beam at `beam_times_s` (B,)
        from each beam's pose (B, 3) (`beam_poses`); the tracks as they are at its last beam."""
        points = scan_points(scan_m, pose, self.beam_angles_rad)
        shapes, static = self._detect(points, pose)
        centres = np.array([shape.centre for shape in shapes]).reshape(-1, 2)
        radii = np.array([shape.radius_m for shape in shapes])
        if beam_times_s is None:
            seen_s = np.full(len(shapes), time_s)
        else:  # each obstacle where it was when the beams that found it were taken
            seen_s = np.array([beam_times_s[shape.beams].mean() for shape in shapes])
            time_s = float(beam_times_s.max())
            span_s, speed = float(np.ptp(beam_times_s)), self.settings.max_obstacle_speed_mps
            latest = seen_once(centres, seen_s, radii, span_s, speed)
            shapes = [shapes[i] for i in latest]
            centres, radii, seen_s = centres[latest], radii[latest], seen_s[latest]
            static = static[latest]
        taken = self._associate(centres, seen_s, time_s, static)
        kept = []
        for index, track in enumerate(self._tracks):
            if index in taken:
                detection = taken[index]
                shape = shapes[detection]
                centre, radius = centres[detection], float(radii[detection])
                known = track.radius_m
                if radius < PARTLY_SEEN * known and len(shape.beams) < MIN_ARC_POINTS:
                    # Partly seen (a few returns past another's edge): too few to place it by
                    # the radius its track knows, it coasts; else placed by that radius.
                    if len(shape.beams) < MIN_KNOWN_POINTS:
                        track.missed += 1
                        kept += [track] if track.missed <= self.settings.coast_frames else []
                        continue
                    beams = points[shape.beams]
                    centre = fit_known_radius(beams, _sensor_xy(pose, shape.beams), known)
                    radius = known
                track.wide = track.wide or shape.wide
                single = len(shape.beams) == 1
                self._extend(track, float(seen_s[detection]), centre, radius, single)
            else:
                track.missed += 1
            if track.missed <= self.settings.coast_frames:
                kept.append(track)
        frames = self.settings.velocity_frames
        for index in sorted(set(range(len(shapes))) - set(taken.values())):
            kept.append(
                _Track(
                    deque([float(seen_s[index])], maxlen=frames),
                    deque([centres[index]], maxlen=frames),
                    deque([float(radii[index])], maxlen=frames),
                    single=len(shapes[index].beams) == 1,
                    wide=shapes[index].wide,
                    static=bool(static[index]),
                )
            )
        self._tracks = kept
        self._time_s = time_s
        return self.tracks()

    def _associate(
        self, centres: F64, seen_s: F64, time_s: float, static: NDArray[np.bool_]
    ) -> dict[int, int]:
        """Track index -> detection index: nearest predictions first, each within its gate, a
        track found where things stand only to a detection found there, and others to others
        (`static`, by detection)."""
        if not self._tracks or not len(centres):
            return {}
        last = np.array([t.centres[-1] for t in self._tracks]).reshape(-1, 2)
        velocity = np.array([t.velocity for t in self._tracks]).reshape(-1, 2)
        elapsed_s = seen_s[None] - np.array([t.times_s[-1] for t in self._tracks])[:, None]
        predicted = last[:, None] + velocity[:, None] * elapsed_s[..., None]  # (tracks, found, 2)
        distance = np.linalg.norm(predicted - centres[None], axis=2)
        gate = np.array([self._gate_m(track, time_s) for track in self._tracks])
        distance[distance > gate[:, None]] = np.inf
        standing = np.array([t.static for t in self._tracks])
        distance[standing[:, None] != static[None]] = np.inf
        taken: dict[int, int] = {}
        for flat in np.argsort(distance, axis=None):
            row, detection = divmod(int(flat), len(centres))
            if not np.isfinite(distance[row, detection]):
                break
            if row not in taken and detection not in taken.values():
                taken[row] = detection
        return taken

    def _gate_m(self, track: _Track, time_s: float) -> float:
        """How far from its prediction a track's next detection may be: a track seen once has
        no velocity yet, so it may have gone as far as the fastest obstacle goes; one seen
        twice has a velocity from two centres only, which may be off by half that."""
        elapsed = time_s - track.times_s[-1]
        reach = self.settings.max_obstacle_speed_mps * elapsed
        if len(track.centres) > 2:
            return self.settings.gate_m
        return self.settings.gate_m + (reach if len(track.centres) == 1 else reach / 2)

    def _extend(
        self, track: _Track, time_s: float, centre: F64, radius_m: float, single: bool
    ) -> None:
        track.times_s.append(time_s)
        track.centres.append(centre)
        track.radii.append(radius_m)
        track.missed = 0
        track.hits += 1
        track.single = track.single and single
        track.velocity = fit_velocity(
            np.array(track.times_s),
            np.array(track.centres),
            max(self.settings.straight_tolerance_m, self.noise_m),
            self._mirrors(track.radius_m),
        )

    def _moving_threshold(self, track: _Track) -> float:
        """The speed below which `track` stands: `moving_speed_mps`, or three standard errors of
        the slope of a line through its centres (as many as it has, over the time they span),
        each centre off by half the range noise, whichever is larger."""
        count = len(track.times_s)
        span_s = track.times_s[-1] - track.times_s[0]
        if count < 2 or span_s <= 0:
            return math.inf
        spacing_s = span_s / (count - 1)
        error = (self.noise_m / 2) / (spacing_s * math.sqrt(count * (count * count - 1) / 12))
        return max(self.settings.moving_speed_mps, 3 * error)

    def _mirrors(self, radius_m: float) -> F64:
        """`bounce_mirrors` of the walls for an obstacle of about `radius_m` (to the millimetre,
        kept)."""
        key = round(radius_m, 3)
        if key not in self._mirror_cache:
            self._mirror_cache[key] = bounce_mirrors(self.walls, key)
        return self._mirror_cache[key]

    def tracks(self) -> Tracks:
        """Every kept track's centre (coasting ones moved on by their velocity; one that stands
        at its recent centres' mean), velocity (zero where it stands: a piece of something wide,
        found where things stand, or slower than `moving_speed_mps` or than three standard
        errors of a velocity fitted under the range noise, `_moving_threshold`) and radius (the
        median of its recent ones); a track found by single returns only once is left out (a
        stray return)."""
        shown = [t for t in self._tracks if not (t.single and t.hits < 2)]
        xy = np.array([t.predicted(self._time_s) for t in shown]).reshape(-1, 2)
        velocity = np.array([t.velocity for t in shown]).reshape(-1, 2)
        threshold = np.array(
            [math.inf if t.wide or t.static else self._moving_threshold(t) for t in shown]
        )
        standing = np.linalg.norm(velocity, axis=1) < threshold
        velocity[standing] = 0.0
        for index in np.flatnonzero(standing):  # where it stands: its recent centres' mean
            xy[index] = np.mean(shown[index].centres, axis=0)
        radius = np.array([t.radius_m for t in shown])
        return Tracks(xy, velocity, radius)
