"""The compiled lidar among many cylinders gives numpy's ranges and clearances."""

import numpy as np
import pytest

from qnav.contracts.observation import LidarSpec
from qnav.sim import barn, raycast
from qnav.sim.geometry import add_circles_to_scan, circles_clearance
from qnav.sim.layouts import load_layouts


@pytest.mark.skipif(not raycast.COMPILED, reason="the compiled lidar was not built here")
@pytest.mark.parametrize("num_beams", [720, 359])
def test_the_compiled_lidar_gives_numpys_ranges_beam_for_beam(num_beams: int) -> None:
    layouts, _ = load_layouts(barn.BARN_FILE)
    rng = np.random.default_rng(7)
    n = 200
    pose = np.stack(
        [rng.uniform(-4.3, -0.2, n), rng.uniform(0.3, 11.0, n), rng.uniform(-4, 4, n)], axis=1
    )
    centres = layouts.cylinder_xy[rng.integers(0, len(layouts), n)]
    lidar = LidarSpec(num_beams, 20.0)
    compiled = np.full((n, num_beams), np.inf, dtype=np.float32)
    gap = np.full(n, np.inf)
    raycast.cast_circles(compiled, gap, pose, lidar, centres, radius_m=0.075, compiled=True)
    reference = np.full((n, num_beams), np.inf, dtype=np.float32)
    add_circles_to_scan(reference, pose, lidar, centres, 0.075)
    np.testing.assert_array_equal(compiled, reference)
    np.testing.assert_array_equal(gap, circles_clearance(pose[:, :2], centres, 0.075))
    # Some poses stand inside a cylinder: every beam reads 0 there, in both.
    assert (compiled == 0).all(axis=1).any()


def test_the_numpy_fallback_lowers_in_place_as_the_compiled_one() -> None:
    pose = np.array([[0.0, 0.0, 0.0]])
    centres = np.array([[[2.0, 0.0], [0.0, -1.0]]])
    lidar = LidarSpec(8, 20.0)
    scan = np.full((1, 8), 1.5, dtype=np.float32)
    gap = np.full(1, 0.5)
    raycast.cast_circles(scan, gap, pose, lidar, centres, radius_m=0.1, compiled=False)
    assert gap[0] == 0.5  # the nearer clearance stays
    # Beam 0 meets the first circle at 1.9 m, beyond what it holds; beam 6 (-90 degrees) the
    # second at 0.9 m.
    np.testing.assert_allclose(scan[0], [1.5] * 6 + [0.9, 1.5])
