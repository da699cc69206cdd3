"""The generator of BARN's family: passable worlds in BARN's frame, disjoint splits."""

import numpy as np

from qnav.sim import barn, clutter
from qnav.sim.layouts import load_layouts


def test_the_corridor_walls_are_barns() -> None:
    published, _ = load_layouts(barn.BARN_FILE)
    ours = {tuple(p) for p in np.round(clutter.corridor_cylinders(), 3)}
    for world in (0, 150, 299):
        count = published.cylinder_count[world]
        theirs = {tuple(p) for p in np.round(published.cylinder_xy[world, :count], 3)}
        assert ours <= theirs
    assert len(ours) == 96


def test_every_generated_world_is_passable_and_the_same_for_its_seed() -> None:
    for family in clutter.FAMILIES:
        for seed in range(5):
            cylinders, start, length = clutter.generate_world(family, seed, "validation")
            again = clutter.generate_world(family, seed, "validation")
            np.testing.assert_array_equal(cylinders, again[0])
            assert np.isfinite(length) and length >= 10.0
            np.testing.assert_allclose(start, barn.START_POSE)
            # Nothing stands within the robot's reach of the start.
            assert np.linalg.norm(cylinders - start[:2], axis=1).min() > 1.0


def test_training_starts_vary_and_splits_do_not_share_worlds() -> None:
    train = clutter.generated_layouts(("cave", "rooms"), "train", 20)
    validation = clutter.generated_layouts(("cave", "rooms"), "validation", 20)
    assert np.ptp(train.start_pose[:, 0]) > 1.0
    seen = {train.cylinder_xy[i, : train.cylinder_count[i]].tobytes() for i in range(20)}
    for i in range(20):
        assert validation.cylinder_xy[i, : validation.cylinder_count[i]].tobytes() not in seen


def test_cylinders_no_ray_can_reach_are_left_out() -> None:
    grid = np.zeros((clutter.FIELD_CELLS, clutter.FIELD_CELLS), dtype=bool)
    grid[10:13, 10:13] = True
    centres = clutter.field_cylinders(grid)
    assert len(centres) == 8
    assert not np.isclose(centres, clutter.cell_xy(np.array([11, 11]))).all(axis=1).any()


def test_a_field_whose_ends_are_not_joined_has_no_path() -> None:
    grid = np.zeros((clutter.FIELD_CELLS, clutter.FIELD_CELLS), dtype=bool)
    grid[:, 15] = True
    start, goal = np.array(barn.START_POSE[:2]), np.array([-2.25, 13.0])
    assert clutter.reference_path_m(clutter.c_space(grid), start, goal) == np.inf
    grid[10:18, 15] = False
    assert np.isfinite(clutter.reference_path_m(clutter.c_space(grid), start, goal))
