from pathlib import Path

import numpy as np
import torch
from PIL import Image

from qnav.contracts.actions import Action
from qnav.sim.config import scenario
from qnav.training.figures import action_grid, draw_action_maps, draw_trajectories, trajectories
from qnav.training.networks import QNetwork


class _AlwaysForward(QNetwork):
    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        q = torch.zeros(frames.shape[0], 3)
        q[:, Action.FORWARD] = 1.0
        return q


def test_action_grid_covers_the_square_around_the_target() -> None:
    network = QNetwork("recurrent", 720, hidden_size=8)
    gx, gy, actions = action_grid(network, scenario("walls-inertia"), window=5)
    assert gx.shape == gy.shape == actions.shape == (11, 11)
    assert gx.min() == -2.0 and gy.max() == 2.0
    assert set(np.unique(actions)) <= {0, 1, 2}


def test_a_robot_driving_straight_at_the_target_reaches_it(tmp_path: Path) -> None:
    world = scenario("toycar-increment")
    # Two starts below the target, both facing it (+y).
    starts = np.array([[5.0, 3.0, np.pi / 2], [4.0, 2.5, np.pi / 2]])
    paths, outcome, target = trajectories(_AlwaysForward("recurrent", None, 8), world, 5, starts)
    assert outcome[0] == 1  # straight up from (5, 3) to (5, 5)
    assert np.allclose(paths[0][:, 0], 5.0)
    png = draw_trajectories(paths, outcome, target, "test", tmp_path / "t.png")
    assert Image.open(png).size[0] > 0
    grid = action_grid(_AlwaysForward("recurrent", None, 8), world, 5)
    assert (grid[2] == Action.FORWARD).all()
    assert Image.open(draw_action_maps([("a", grid)], tmp_path / "a.png")).size[0] > 0
