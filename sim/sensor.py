"""What a real lidar and motion capture add to the exact world (`sim.config.SensorConfig`): the
lidar's own number of readings, resampled to the policy's beams as the controller resamples
them; range noise; readings that return nothing; a blocked sector; and a motion-capture pose
that is noisy and late.

Every draw is a pure function of the world's (seed, episode) and its step (`sim.rng`), so a
world's noise is the same alone or in a batch of any size.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import wrap_angle
from qnav.sim import rng
from qnav.sim.config import SensorConfig, WorldConfig

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

_RANGE_NOISE, _DROPOUT, _POSE_NOISE = 60, 62, 63
"""Random streams of a world's key at each step (`step_keys`)."""


def step_keys(seed: I64, episode: I64, steps: I64) -> NDArray[np.uint64]:
    """(N,) a key per world for the draws of its current step."""
    return rng.episode_keys(rng.episode_keys(seed, episode), steps)


def normal(keys: NDArray[np.uint64], stream: int, shape: tuple[int, ...]) -> F64:
    """Standard normal draws of shape keys.shape + shape (Box-Muller on two streams)."""
    u1, u2 = rng.uniform(keys, stream, shape), rng.uniform(keys, stream + 100, shape)
    return np.asarray(np.sqrt(-2.0 * np.log1p(-u1)) * np.cos(2 * math.pi * u2))


def readings_of(config: WorldConfig) -> int:
    """The physical lidar's readings per turn (the policy's beams unless set)."""
    assert config.lidar is not None
    return config.sensor.lidar_readings or config.lidar.num_beams


@cache
def beam_readings(readings: int, beams: int) -> I64:
    """(B, K) the readings whose sectors overlap each beam's by more than a thousandth of the
    narrower sector (docs/controller.md, "Scan resampling", rule 3), padded with repeats: beam j
    centred at j 2 pi / B, reading i at i 2 pi / R, each as wide as the spacing of its kind."""
    ratio = beams // readings
    centre = np.arange(beams) / ratio  # in reading widths
    low, high = centre - 0.5 / ratio, centre + 0.5 / ratio
    narrower = 1.0 / ratio
    rows = []
    for j in range(beams):
        first, last = math.floor(low[j] + 0.5) - 1, math.ceil(high[j] - 0.5) + 1
        hits = [
            i % readings
            for i in range(first, last + 1)
            if min(high[j], i + 0.5) - max(low[j], i - 0.5) > 1e-3 * narrower
        ]
        rows.append(hits)
    width = max(len(row) for row in rows)
    return np.array([row + [row[0]] * (width - len(row)) for row in rows], dtype=np.int64)


def sensed_scans(
    sensor: SensorConfig, beams: int, scans_m: NDArray[np.float32], keys: NDArray[np.uint64]
) -> NDArray[np.float32]:
    """(N, B) what the policy reads of the lidar's readings (N, R), each world's draws from its
    step's key (`step_keys`): the blocked sector and the dropouts return nothing (+inf), the rest
    get range noise (kept at 0 m or more), then the readings are resampled to the beams (each
    beam the nearest of the readings its sector overlaps)."""
    readings = scans_m.shape[1]
    ranges = scans_m.astype(np.float64)
    if sensor.blocked_width_rad:
        angle = np.arange(readings) * (2 * math.pi / readings)
        offset = np.abs(wrap_angle(angle - sensor.blocked_centre_rad))
        ranges[:, offset <= sensor.blocked_width_rad / 2] = np.inf
    if sensor.dropout:
        ranges[rng.uniform(keys, _DROPOUT, (readings,)) < sensor.dropout] = np.inf
    if sensor.range_noise_m:
        noise = sensor.range_noise_m * normal(keys, _RANGE_NOISE, (readings,))
        ranges = np.where(np.isfinite(ranges), np.maximum(ranges + noise, 0.0), ranges)
    if readings != beams:
        ranges = ranges[:, beam_readings(readings, beams)].min(-1)
    return ranges.astype(np.float32)


def measured_poses(sensor: SensorConfig, poses: F64, keys: NDArray[np.uint64]) -> F64:
    """(N, 3) the motion-capture poses the car reads from the true poses (N, 3) at the
    instant the system measured them: Gaussian noise on each coordinate and on the heading."""
    noise = normal(keys, _POSE_NOISE, (3,))
    scale = np.array([sensor.pose_noise_m, sensor.pose_noise_m, sensor.pose_noise_rad])
    measured: F64 = poses + noise * scale
    measured[:, 2] = wrap_angle(measured[:, 2])
    return measured
