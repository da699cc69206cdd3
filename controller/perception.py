"""Moving obstacles from a lidar and a motion-capture pose: a small tracker, numpy only.

The paper's network is asked to find moving obstacles in raw ranges; measured, it does not
(docs/learner.md, "Why: perception and the doom function's appetite for data"). Indoors the car
knows its pose (motion capture) and the room's walls, which makes the job classical and cheap:

1. every return becomes a point in the room's frame (`scan_points`), placed from the car's pose
   when it was taken (`beam_poses`: a rotating lidar's beams leave over its turn);
2. returns on a known wall are the wall (`off_the_walls`); the rest is grouped into runs of
   neighbouring beams (`clusters`);
3. each cluster is the near side of a cylinder of known radius, whose centre a least-squares
   fit finds (`fit_circle`);
4. detections join tracks by nearest prediction within a gate; a track's velocity is the slope
   of a straight-line fit to its recent centres, over the longest recent stretch that is
   straight (an obstacle that bounced off a wall starts a new stretch) (`fit_velocity`).

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

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class TrackerSettings:
    """How the tracker reads a scan and keeps its tracks."""

    SECTION = "tracker"

    obstacle_radius_m: float = 0.2
    """Radius of the (cylindrical) obstacles the circle fit assumes."""
    wall_band_m: float = 0.1
    """Returns within this distance of a known wall belong to the wall (keep it above three
    times the lidar's range noise, or the walls' noisy returns become obstacles)."""
    min_returns: int = 3
    """Fewest neighbouring returns that make an obstacle (a lone stray return does not)."""
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
    """Largest residual of a centre from the fitted line for a stretch to count as straight."""
    coast_frames: int = 3
    """Scans a track is kept (moved by its velocity) without a detection (3: 0.6 s at 5 Hz;
    scale it with the lidar's rate as `velocity_frames`)."""

    def __post_init__(self) -> None:
        check_range(
            self, "obstacle_radius_m", self.obstacle_radius_m, 0.0, 100.0, exclusive_low=True
        )
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


WIDEST_ARC = 2.4
"""A run of returns wider (first to last point) than this many obstacle radii is not one
cylinder, whose near side spans at most two radii (the rest allows for range noise): it is
obstacles side by side, merged in the scan."""


CLUTTER_ARC = 8.0
"""A run wider than this many obstacle radii (four obstacles side by side) is not a few merged
obstacles but something long the room's walls do not explain (furniture, a wall placed from the
wrong pose): it is cut into pieces one obstacle wide, in one pass, where searching for the best
cuts would cost time quadratic in its length (up to 0.2 s a scan, docs/controller.md)."""


def split_wide(
    run: NDArray[np.int64], points: F64, sensor_xy: F64, radius_m: float
) -> list[NDArray[np.int64]]:
    """`run` (beam indices, in scan order) as the runs of single obstacles: one too wide to be
    one is cut where the circle fits of the two sides leave the least residual, and each side
    again if need be; one wider than `CLUTTER_ARC` radii is cut into pieces one obstacle wide
    (`one_wide_pieces`)."""
    ends = points[run[-1]] - points[run[0]]
    width_m = float(np.hypot(*ends))
    if len(run) < 6 or width_m <= WIDEST_ARC * radius_m:
        return [run]
    if width_m > CLUTTER_ARC * radius_m:
        return one_wide_pieces(run, points, 2 * radius_m)
    best, cut = np.inf, 0
    for k in range(3, len(run) - 2):
        residual = sum(
            _fit_residual(points[side], sensor_xy, radius_m) for side in (run[:k], run[k:])
        )
        if residual < best:
            best, cut = residual, k
    return [
        *split_wide(run[:cut], points, sensor_xy, radius_m),
        *split_wide(run[cut:], points, sensor_xy, radius_m),
    ]


def one_wide_pieces(run: NDArray[np.int64], points: F64, width_m: float) -> list[NDArray[np.int64]]:
    """`run` cut into consecutive pieces whose points lie within `width_m` of the piece's first."""
    pieces, start = [], 0
    first = points[run[0]]
    for k in range(1, len(run)):
        if float(np.hypot(*(points[run[k]] - first))) > width_m:
            pieces.append(run[start:k])
            start, first = k, points[run[k]]
    pieces.append(run[start:])
    return pieces


def _fit_residual(points: F64, sensor_xy: F64, radius_m: float) -> float:
    centre = fit_circle(points, sensor_xy, radius_m)
    return float(np.sum((np.linalg.norm(points - centre, axis=1) - radius_m) ** 2))


def fit_circle(points: F64, sensor_xy: F64, radius_m: float, iterations: int = 5) -> F64:
    """(2,) centre of the circle of `radius_m` whose near side best fits `points` (P, 2) seen
    from `sensor_xy`: Gauss-Newton on the radial residuals, from the points' centroid pushed
    back by the radius along the line of sight."""
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


def seen_once(centres: F64, seen_s: F64, diameter_m: float, span_s: float) -> NDArray[np.int64]:
    """Indices of the detections (D, 2) to keep from a rotating lidar's scan, whose beams at the
    seam (its first and last) may see one obstacle twice, a turn apart: of two detections less
    than a diameter apart and seen more than half the scan's span (`span_s`) apart in time, the
    later (obstacles that overlap are seen at once, and both are kept)."""
    kept: list[int] = []
    for index in np.argsort(-seen_s, kind="stable"):
        twice = any(
            np.linalg.norm(centres[index] - centres[other]) < diameter_m
            and seen_s[other] - seen_s[index] > span_s / 2
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
    """(K, 2) obstacle velocities."""


@dataclass
class _Track:
    times_s: deque[float]
    centres: deque[F64]
    velocity: F64 = field(default_factory=lambda: np.zeros(2))
    missed: int = 0

    def predicted(self, time_s: float) -> F64:
        return np.asarray(self.centres[-1] + self.velocity * (time_s - self.times_s[-1]))


class ObstacleTracker:
    """One room's obstacle tracks, updated with each scan and the pose it was taken from."""

    def __init__(self, settings: TrackerSettings, walls: F64, beam_angles_rad: F64) -> None:
        self.settings = settings
        self.walls = walls
        self.mirrors = bounce_mirrors(walls, settings.obstacle_radius_m)
        self.beam_angles_rad = beam_angles_rad
        self._tracks: list[_Track] = []
        self._time_s = 0.0

    def detect(self, scan_m: NDArray[np.floating], pose: F64) -> F64:
        """(D, 2) obstacle centres found in one scan seen from `pose` (as `scan_points`)."""
        return self._detect(scan_m, pose)[0]

    def _detect(
        self, scan_m: NDArray[np.floating], pose: F64
    ) -> tuple[F64, list[NDArray[np.int64]]]:
        """`detect`'s centres, and the beams each was found in."""
        s = self.settings
        points = scan_points(scan_m, pose, self.beam_angles_rad)
        runs = clusters(points, off_the_walls(points, self.walls, s.wall_band_m), s.cluster_gap_m)
        pieces = [
            piece
            for run in runs
            for piece in split_wide(run, points, _sensor_xy(pose, run), s.obstacle_radius_m)
            if len(piece) >= s.min_returns
        ]
        centres = [
            fit_circle(points[piece], _sensor_xy(pose, piece), s.obstacle_radius_m)
            for piece in pieces
        ]
        return np.array(centres, dtype=np.float64).reshape(-1, 2), pieces

    def update(
        self,
        time_s: float,
        scan_m: NDArray[np.floating],
        pose: F64,
        beam_times_s: F64 | None = None,
    ) -> Tracks:
        """Take in a scan taken at `time_s` from `pose`, or beam by beam at `beam_times_s` (B,)
        from each beam's pose (B, 3) (`beam_poses`); the tracks as they are at its last beam."""
        s = self.settings
        detections, pieces = self._detect(scan_m, pose)
        if beam_times_s is None:
            seen_s = np.full(len(detections), time_s)
        else:  # each obstacle where it was when the beams that found it were taken
            seen_s = np.array([beam_times_s[piece].mean() for piece in pieces])
            time_s = float(beam_times_s.max())
            span_s = float(np.ptp(beam_times_s))
            latest = seen_once(detections, seen_s, 2 * s.obstacle_radius_m, span_s)
            detections, seen_s = detections[latest], seen_s[latest]
        last = np.array([t.centres[-1] for t in self._tracks]).reshape(-1, 2)
        velocity = np.array([t.velocity for t in self._tracks]).reshape(-1, 2)
        elapsed_s = seen_s[None] - np.array([t.times_s[-1] for t in self._tracks])[:, None]
        predicted = last[:, None] + velocity[:, None] * elapsed_s[..., None]  # (tracks, found, 2)
        taken_tracks: set[int] = set()
        taken_detections: set[int] = set()
        if len(predicted) and len(detections):
            distance = np.linalg.norm(predicted - detections[None], axis=2)
            gate = np.array([self._gate_m(track, time_s) for track in self._tracks])
            distance[distance > gate[:, None]] = np.inf
            for flat in np.argsort(distance, axis=None):
                row, detection = divmod(int(flat), len(detections))
                if not np.isfinite(distance[row, detection]):
                    break
                if row in taken_tracks or detection in taken_detections:
                    continue
                taken_tracks.add(row)
                taken_detections.add(detection)
                self._extend(self._tracks[row], float(seen_s[detection]), detections[detection])
        kept = []
        for index, track in enumerate(self._tracks):
            if index not in taken_tracks:
                track.missed += 1
            if track.missed <= s.coast_frames:
                kept.append(track)
        for index, centre in enumerate(detections):
            if index not in taken_detections:
                kept.append(
                    _Track(
                        deque([float(seen_s[index])], maxlen=s.velocity_frames),
                        deque([centre], maxlen=s.velocity_frames),
                    )
                )
        self._tracks = kept
        self._time_s = time_s
        return self.tracks()

    def _gate_m(self, track: _Track, time_s: float) -> float:
        """How far from its prediction a track's next detection may be: a track seen once has
        no velocity yet, so it may have gone as far as the fastest obstacle goes."""
        if len(track.centres) > 1:
            return self.settings.gate_m
        elapsed = time_s - track.times_s[-1]
        return self.settings.gate_m + self.settings.max_obstacle_speed_mps * elapsed

    def _extend(self, track: _Track, time_s: float, centre: F64) -> None:
        track.times_s.append(time_s)
        track.centres.append(centre)
        track.missed = 0
        track.velocity = fit_velocity(
            np.array(track.times_s),
            np.array(track.centres),
            self.settings.straight_tolerance_m,
            self.mirrors,
        )

    def tracks(self) -> Tracks:
        """Every kept track's centre (coasting ones moved on by their velocity) and velocity."""
        xy = np.array([t.predicted(self._time_s) for t in self._tracks]).reshape(-1, 2)
        velocity = np.array([t.velocity for t in self._tracks]).reshape(-1, 2)
        return Tracks(xy, velocity)
