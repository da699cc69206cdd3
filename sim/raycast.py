"""The lidar and the clearance among a layout's many cylinders: the compiled loop
(`sim/_raycast.c`) where the install built it, else numpy's `sim.geometry` (the same ranges).

`qnav bench sim --barn` says which one runs.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.observation import LidarSpec
from qnav.sim.geometry import add_circles_to_scan, circles_clearance, lidar_angles_f64

try:
    from qnav.sim import _raycast  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover - an install without a C compiler
    _raycast = None

F64 = NDArray[np.float64]

COMPILED = _raycast is not None
"""Whether the compiled loop is installed."""


def cast_circles(
    ranges: NDArray[np.float32],
    clearance_m: F64,
    pose: F64,
    lidar: LidarSpec | None,
    centre_xy: F64,
    *,
    radius_m: float,
    compiled: bool = COMPILED,
) -> None:
    """Lower scans (N, B) to each beam's nearest circle (N, M, 2) and clearances (N,) to each
    robot's nearest circle surface, in place (`sim.geometry.add_circles_to_scan` and
    `circles_clearance`); no scan is cast without a lidar."""
    if not compiled or lidar is None:
        if lidar is not None:
            add_circles_to_scan(ranges, pose, lidar, centre_xy, radius_m)
        np.minimum(clearance_m, circles_clearance(pose[:, :2], centre_xy, radius_m), clearance_m)
        return
    n, m = centre_xy.shape[:2]
    beam_cos, beam_sin = lidar_angles_f64(lidar)
    _raycast.cast_circles(
        np.ascontiguousarray(pose, dtype=np.float64),
        np.ascontiguousarray(centre_xy, dtype=np.float64),
        float(radius_m),
        beam_cos,
        beam_sin,
        lidar.angle_increment_rad,
        lidar.max_range_m,
        1.0,
        ranges,
        clearance_m,
        n,
        m,
        lidar.num_beams,
    )
