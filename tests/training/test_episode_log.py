"""Rounds on disk: what is written is what is read, and older files still read."""

from pathlib import Path

import numpy as np

from qnav.training.episode_log import Episode, read_rounds, write_round


def _episode(steps: int) -> Episode:
    rng = np.random.default_rng(steps)
    return Episode(
        pose=rng.random((steps + 1, 3)),
        scan_m=rng.random((steps + 1, 8), dtype=np.float32),
        clearance_m=rng.random(steps + 1),
        action=rng.integers(0, 3, steps),
        target_xy=rng.random(2),
        outcome=1,
    )


def test_a_written_round_reads_back_episode_for_episode(tmp_path: Path) -> None:
    episodes = [_episode(3), _episode(5)]
    write_round(tmp_path, 0, episodes)
    (read,) = read_rounds(tmp_path)
    for got, wanted in zip(read, episodes, strict=True):
        for name in Episode._fields:
            np.testing.assert_array_equal(getattr(got, name), getattr(wanted, name), name)


def test_a_round_written_while_demonstrations_existed_still_reads(tmp_path: Path) -> None:
    # Rounds written up to commit b8dfe92 also hold a `demonstrated` flag per episode.
    episodes = [_episode(3), _episode(4)]
    path = write_round(tmp_path, 0, episodes)
    with np.load(path) as data:
        older = {name: data[name] for name in data.files}
    np.savez(path, **older, demonstrated=np.array([False, False]))
    (read,) = read_rounds(tmp_path)
    for got, wanted in zip(read, episodes, strict=True):
        for name in Episode._fields:
            np.testing.assert_array_equal(getattr(got, name), getattr(wanted, name), name)


def test_an_episode_read_back_holds_only_its_own_frames(tmp_path: Path) -> None:
    """A view into its round's arrays would keep the whole round (and, read member by member,
    a fresh copy of it per episode) alive: 14 GB for seven DAgger rounds of 64 episodes."""
    episodes = [_episode(20 + i) for i in range(4)]
    write_round(tmp_path, 0, episodes)
    for episode in read_rounds(tmp_path)[0]:
        for array in (episode.pose, episode.scan_m, episode.clearance_m, episode.action):
            assert array is not None and array.base is None
