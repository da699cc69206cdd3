"""Any lidar's LaserScan resampled to the policy's beams (`contracts.observation.LidarSpec`).

The policy reads B beams, beam j pointing at j * 2*pi/B counter-clockwise from the car's
heading. A real scan has its own count, start angle, direction (a negative increment is a
clockwise scan) and mounting. The rule, the same for finer and coarser scans:

1. Reading i of the scan points at `mount_yaw + angle_min + i * angle_increment` in the car's
   frame and covers the sector of width |angle_increment| centred there. Policy beam j covers
   the sector of width 2*pi/B centred on its own angle. (`angle_max` is not used: drivers
   disagree on whether it is inclusive.)
2. Each reading is cleaned first (REP 117): +inf or a value above range_max is no return (+inf,
   which the policy reads as its maximum range); -inf (closer than range_min) is an obstacle at
   0 m; NaN is invalid; a finite value below range_min (0 included) is invalid, no return or an
   obstacle at 0 m as `lidar.below_range_min` says.
3. Beam j reads the minimum of the valid readings whose sectors overlap its own (by more than a
   thousandth of the narrower sector, so sectors that merely touch do not count). The minimum is
   the safe choice: an obstacle seen by any reading in the sector is kept. For a scan of the
   policy's own layout this is the identity; a coarser scan gives each beam the nearer of the
   one or two readings around it.
4. A beam that no valid reading overlaps (outside a partial field of view, or only invalid
   readings) reads `lidar.uncovered_range_m` (+inf by default: no return).
5. A rotating lidar takes its readings one after another (LaserScan's time_increment): beam j
   was taken the index of its first overlapping reading times time_increment after the stamp
   (`Resampled.delays_s`), which the obstacle tracker uses to place each beam from where the car
   was then (`controller.lookahead`).

The mapping from readings to beams depends only on the scan's layout, so it is computed once
per layout and cached; resampling a scan is then a few passes over its readings to clean
them, one gather and (for a scan finer than the policy's beams) one minimum per beam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.wire import Scan

BelowRangeMin = Literal["invalid", "no_return", "obstacle"]

_OVERLAP_TOLERANCE = 1e-3
"""Sectors must overlap by more than this fraction of the narrower one to count."""


@dataclass(frozen=True)
class ScanRules:
    """How readings are cleaned and mapped (the `[lidar]` settings, without the frame check)."""

    num_beams: int
    """Beams of the policy."""
    mount_yaw_rad: float = 0.0
    """Yaw of the lidar's x axis from the car's heading, counter-clockwise."""
    below_range_min: BelowRangeMin = "invalid"
    """What a finite reading below range_min means."""
    uncovered_range_m: float = math.inf
    """What a beam without any valid reading reads."""


@dataclass(frozen=True)
class Resampled:
    """A scan in the policy's beam layout."""

    ranges_m: NDArray[np.float32]
    """(num_beams,) ranges; +inf is no return."""
    invalid_fraction: float
    """Fraction of the scan's readings that were invalid (NaN, or below range_min if so ruled)."""
    delays_s: NDArray[np.float64] | None = None
    """(num_beams,) when each beam was taken, in seconds after the stamp (None: all at the
    stamp, a scan without a time_increment)."""


_BELOW_RANGE_MIN: dict[BelowRangeMin, float] = {
    "invalid": math.nan,
    "no_return": math.inf,
    "obstacle": 0.0,
}
"""What a finite reading below range_min becomes under each rule (NaN: invalid)."""


def clean_readings(scan: Scan, below_range_min: BelowRangeMin) -> tuple[NDArray[np.float64], float]:
    """The readings as the rule reads them, NaN where a reading is invalid, followed by two NaN
    slots (the padding of `beam_index`'s table); and the fraction of invalid readings.

    NaN for "invalid" lets one NaN-ignoring minimum do what a mask of valid readings would,
    and every mask is taken from the raw readings before any is changed.
    """
    count = len(scan.ranges_m)
    values = np.empty(count + 2)
    values[count:] = math.nan
    readings = values[:count]
    readings[:] = scan.ranges_m  # float32 -> float64, exact: thresholds compare in float64
    beyond = readings > scan.range_max_m  # no return (+inf already reads as one)
    closer = readings == -math.inf  # closer than the sensor measures: an obstacle at 0 m
    below = (readings < scan.range_min_m) & ~closer  # finite and below (NaN compares false)
    readings[beyond] = math.inf
    readings[closer] = 0.0
    readings[below] = _BELOW_RANGE_MIN[below_range_min]
    # 1 - valid / count, as the mean of a validity mask gives it (empty scan: NaN).
    valid = count - int(np.count_nonzero(np.isnan(readings)))
    invalid_fraction = 1.0 - valid / count if count else math.nan
    return values, invalid_fraction


def resample_scan(scan: Scan, rules: ScanRules) -> Resampled:
    """The scan as the policy's beams (module docstring: the rule)."""
    values, invalid_fraction = clean_readings(scan, rules.below_range_min)
    index = beam_index(
        len(scan.ranges_m),
        scan.angle_min_rad,
        scan.angle_increment_rad,
        rules.num_beams,
        rules.mount_yaw_rad,
    )
    # The minimum over each beam's row, one column at a time (numpy reduces a short trailing
    # axis slowly); fmin ignores the NaN of invalid readings and of the padding. A scan in the
    # policy's own layout has one column: a gather is the whole job.
    beams = values[index[:, 0]]
    for column in range(1, index.shape[1]):
        np.fmin(beams, values[index[:, column]], out=beams)
    beams[np.isnan(beams)] = rules.uncovered_range_m  # no valid reading overlaps the beam
    delays_s = None
    if scan.time_increment_s > 0.0:
        first = first_readings(
            len(scan.ranges_m),
            scan.angle_min_rad,
            scan.angle_increment_rad,
            rules.num_beams,
            rules.mount_yaw_rad,
        )
        delays_s = scan.time_increment_s * first
    return Resampled(beams.astype(np.float32), invalid_fraction, delays_s)


@lru_cache(maxsize=16)
def first_readings(
    count: int, angle_min_rad: float, increment_rad: float, num_beams: int, mount_yaw_rad: float
) -> NDArray[np.float64]:
    """(num_beams,) the index of the first reading overlapping each beam (`beam_index`'s table;
    0 for a beam none overlaps), cached per layout as that table is. The first, not the mean: a
    beam at the scan's seam overlaps its last reading and its first, a whole turn apart."""
    index = beam_index(count, angle_min_rad, increment_rad, num_beams, mount_yaw_rad)
    first = np.where(index < count, index, count).min(axis=1)
    result = np.where(first < count, first, 0).astype(np.float64)
    result.setflags(write=False)
    return result


@lru_cache(maxsize=16)
def beam_index(
    count: int, angle_min_rad: float, increment_rad: float, num_beams: int, mount_yaw_rad: float
) -> NDArray[np.intp]:
    """(num_beams, K) reading indices overlapping each beam, padded with `count` (neutral);
    a beam that no reading overlaps holds only `count + 1` (uncovered)."""
    two_pi = 2.0 * math.pi
    beam_width = two_pi / num_beams
    reading_width = abs(increment_rad)
    reach = (reading_width + beam_width) / 2 - _OVERLAP_TOLERANCE * min(reading_width, beam_width)
    centres = np.mod(mount_yaw_rad + angle_min_rad + np.arange(count) * increment_rad, two_pi)
    first = np.floor((centres - reach) / beam_width).astype(np.int64) + 1
    last = np.ceil((centres + reach) / beam_width).astype(np.int64) - 1
    spans = np.minimum(last - first + 1, num_beams)
    readings = np.repeat(np.arange(count), spans)
    offsets = np.arange(int(spans.sum())) - np.repeat(np.cumsum(spans) - spans, spans)
    beams = np.mod(np.repeat(first, spans) + offsets, num_beams)
    # One row per beam: sort the (beam, reading) pairs by beam and pad the rows.
    order = np.lexsort((readings, beams))
    beams, readings = beams[order], readings[order]
    per_beam = np.bincount(beams, minlength=num_beams)
    width = max(int(per_beam.max()), 1)
    index = np.full((num_beams, width), count, dtype=np.intp)
    index[per_beam == 0, 0] = count + 1
    column = np.arange(len(beams)) - np.repeat(np.cumsum(per_beam) - per_beam, per_beam)
    index[beams, column] = readings
    index.setflags(write=False)
    return index
