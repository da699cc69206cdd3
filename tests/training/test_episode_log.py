"""Rounds on disk: what is written is what is read, and older files still read."""

from pathlib import Path

import numpy as np

from training.episode_log import read_rounds, write_round
from training.replay import Episode


def _episode(steps: int, demonstrated: bool) -> Episode:
    rng = np.random.default_rng(steps)
    return Episode(
        pose=rng.random((steps + 1, 3)),
        scan_m=rng.random((steps + 1, 8), dtype=np.float32),
        clearance_m=rng.random(steps + 1),
        action=rng.integers(0, 3, steps),
        target_xy=rng.random(2),
        outcome=1,
        demonstrated=demonstrated,
    )


def test_a_written_round_reads_back_episode_for_episode(tmp_path: Path) -> None:
    episodes = [_episode(3, True), _episode(5, False)]
    write_round(tmp_path, 0, episodes)
    (read,) = read_rounds(tmp_path)
    for got, wanted in zip(read, episodes, strict=True):
        for name in Episode._fields:
            np.testing.assert_array_equal(getattr(got, name), getattr(wanted, name), name)


def test_a_round_written_before_demonstrations_existed_reads_as_undemonstrated(
    tmp_path: Path,
) -> None:
    path = write_round(tmp_path, 0, [_episode(3, True)])
    with np.load(path) as data:
        older = {name: data[name] for name in data.files if name != "demonstrated"}
    np.savez(path, **older)
    (read,) = read_rounds(tmp_path)
    assert read[0].demonstrated is False
