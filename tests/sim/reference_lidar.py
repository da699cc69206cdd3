"""A slow, obviously correct lidar: every ray against every wall segment and circle, in float64."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from qnav.sim.config import WorldConfig
from qnav.sim.geometry import wall_segments


def reference_scan(
    config: WorldConfig, pose: NDArray[np.float64], obstacle_xy: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Ranges of one pose (3,) with obstacles (M, 2); +inf beyond the maximum range."""
    assert config.lidar is not None
    segments = wall_segments(config.arena)
    angles = pose[2] + config.lidar.beam_angles_rad()
    ranges = np.full(angles.shape, np.inf)
    origin = pose[:2]
    for index, angle in enumerate(angles):
        direction = np.array([np.cos(angle), np.sin(angle)])
        best = np.inf
        for start, end in zip(segments.start, segments.end, strict=True):
            # Solve origin + t * direction = start + s * (end - start), t >= 0, s in [0, 1].
            span = end - start
            matrix = np.array([direction, -span]).T
            if abs(np.linalg.det(matrix)) < 1e-12:
                continue
            t, s = np.linalg.solve(matrix, start - origin)
            if t >= 0 and 0 <= s <= 1:
                best = min(best, t)
        for centre in obstacle_xy:
            offset = centre - origin
            along = offset @ direction
            disc = along**2 - (offset @ offset - config.obstacles.radius_m**2)
            if disc >= 0:
                near = along - np.sqrt(disc)
                if near >= 0:
                    best = min(best, near)
        ranges[index] = best if best <= config.lidar.max_range_m else np.inf
    return ranges
