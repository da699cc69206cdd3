"""Episode pictures: the record is faithful to the simulator and the files it draws are readable."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings, RandomAgent, evaluate
from qnav.sim.render import draw_gif, draw_png, record_episode, render_episode
from qnav.sim.world import Observation

pytest.importorskip("matplotlib")
Image = pytest.importorskip("PIL.Image")


def test_png_and_gif_are_written_and_readable(tmp_path: Path) -> None:
    config = scenario("obstacles-inertia")
    png, gif = render_episode(
        config, RandomAgent(1, seed=0), tmp_path / "out", seed=0, rays=True, max_steps=15
    )
    assert png == tmp_path / "out" / "obstacles-inertia-seed0-ep0.png"
    assert gif == tmp_path / "out" / "obstacles-inertia-seed0-ep0.gif"
    record = record_episode(config, RandomAgent(1, seed=0), seed=0, max_steps=15)
    with Image.open(png) as image:
        assert image.format == "PNG"
        assert image.size[0] > 0 and image.size[1] > 0
    with Image.open(gif) as image:
        assert image.format == "GIF"
        assert image.n_frames == record.steps + 1


def test_gif_with_stride_still_ends_on_the_last_step(tmp_path: Path) -> None:
    record = record_episode(
        scenario("walls-increment"), RandomAgent(1, seed=4), seed=2, max_steps=7
    )
    assert record.steps == 7  # 0, 3, 6 by stride, then 7 so the ending is shown
    gif = draw_gif(record, tmp_path / "strided.gif", stride=3, fps=5)
    with Image.open(gif) as image:
        assert image.n_frames == 4
        assert image.info["duration"] == 200


def test_record_stops_at_termination() -> None:
    config = scenario("obstacles-inertia")
    record = record_episode(config, RandomAgent(1, seed=0), seed=3)
    steps = record.steps
    assert record.outcome != Outcome.RUNNING
    assert steps < config.max_episode_steps
    assert len(record.actions) == len(record.rewards) == len(record.poses) - 1 == steps
    assert record.obstacle_xy.shape == (steps + 1, config.obstacles.count, 2)
    assert record.scans is not None and config.lidar is not None
    assert record.scans.shape == (steps + 1, config.lidar.num_beams)
    assert record.scans.dtype == np.float32
    final_reward = {
        Outcome.SUCCESS: config.reward.success_reward,
        Outcome.COLLISION: config.reward.collision_reward,
    }[record.outcome]
    assert record.rewards[-1] == final_reward
    assert np.all(np.abs(record.rewards[:-1]) < 1.0)  # no earlier step ended the episode


def test_record_truncated_at_step_limit_is_running() -> None:
    class Spin:
        """Turns in place, far from every wall, so only the step limit can end the episode."""

        def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
            pass

        def act(self, observation: Observation) -> NDArray[np.int64]:
            return np.array([1], dtype=np.int64)

    record = record_episode(scenario("walls-increment"), Spin(), seed=0, max_steps=12)
    assert record.steps == 12
    assert record.outcome == Outcome.RUNNING
    assert record.config.max_episode_steps == 12
    assert np.allclose(record.poses[:, :2], record.poses[0, :2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_record_matches_evaluation_of_the_same_seed_and_episode(seed: int) -> None:
    config = scenario("obstacles-inertia")
    settings = EvalSettings(episodes=1, max_episode_steps=60, num_worlds=1, seed=seed)
    result = evaluate(config, RandomAgent(1, seed=5), settings)
    record = record_episode(config, RandomAgent(1, seed=5), seed=seed, max_steps=60)
    assert record.steps == result.mean_steps
    assert (record.outcome == Outcome.SUCCESS) == (result.success == 1.0)
    assert (record.outcome == Outcome.COLLISION) == (result.collision == 1.0)


def test_lidarless_scenario_renders(tmp_path: Path) -> None:
    config = scenario("toycar-inertia")
    record = record_episode(config, RandomAgent(1, seed=0), seed=1, max_steps=10)
    assert record.scans is None
    assert record.obstacle_xy.shape == (record.steps + 1, 0, 2)
    png = draw_png(record, tmp_path / "toycar.png", rays=True)
    gif = draw_gif(record, tmp_path / "toycar.gif", rays=True)
    with Image.open(png) as image:
        assert image.size[0] > 0
    with Image.open(gif) as image:
        assert image.n_frames == record.steps + 1


def test_missing_plotting_libraries_raise_the_install_hint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    record = record_episode(scenario("walls-inertia"), RandomAgent(1), seed=0, max_steps=3)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'qnav\[viz\]'"):
        draw_png(record, tmp_path / "never.png")
    assert not (tmp_path / "never.png").exists()
