"""The calibration table runs at any episode count (its worlds side by side are capped by it)."""

from qnav.lab.calibrate import calibrate
from qnav.sim.config import scenario


def test_fewer_episodes_than_worlds_side_by_side_still_calibrate() -> None:
    rows = calibrate(
        {"obstacles-increment": scenario("obstacles-increment")},
        episodes=12,
        oracle_episodes=3,
        seed=1,
    )
    (row,) = rows
    assert row.random.episodes == row.goto.episodes == 12
    assert row.oracle is not None and row.oracle.episodes == 3
