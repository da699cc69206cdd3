"""`lab.redrawn`: doom labels from a training run's own stored steps among re-drawn obstacles."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import step_robot
from qnav.contracts.observation import distance_scale_m, encode_target, target_features
from qnav.lab.decisive import GaugeSettings, is_decisive
from qnav.lab.oracle import collision_shares
from qnav.lab.probe import ProbeSettings, probe
from qnav.lab.redrawn import STORED_PATH, redrawn_states, stored_steps
from qnav.sim.config import scenario
from tests.lab.conftest import TINY_RUN_WORLD as WORLD


def test_stored_steps_replay_their_actions_to_the_next_stored_pose(tiny_run: Path) -> None:
    steps = stored_steps(WORLD, tiny_run, window=5)
    assert len(steps.pose) > 0 and np.abs(steps.velocity).max() > 0
    pose, _ = step_robot(
        steps.pose, steps.velocity, steps.action, WORLD.dynamics, WORLD.control_period_s
    )
    same_episode = steps.episode[1:] == steps.episode[:-1]
    np.testing.assert_allclose(pose[:-1][same_episode], steps.pose[1:][same_episode], atol=1e-9)
    # Each window ends on its own step and stays inside its episode.
    np.testing.assert_array_equal(steps.window[:, -1], np.arange(len(steps.pose)))
    assert (steps.episode[steps.window] == steps.episode[:, None]).all()


def test_redrawn_states_are_labelled_by_the_planner_where_the_run_went(tiny_run: Path) -> None:
    states = redrawn_states(WORLD, tiny_run, 600, window=5, ordinary_share=0.2, seed=4)
    again = redrawn_states(WORLD, tiny_run, 600, window=5, ordinary_share=0.2, seed=4)
    np.testing.assert_array_equal(states.collide_share, again.collide_share)
    assert is_decisive(states.doomed).any() and not is_decisive(states.doomed).all()
    relabelled = collision_shares(WORLD, states.world).astype(np.float32)
    np.testing.assert_array_equal(states.collide_share, relabelled)
    assert (states.driver == STORED_PATH).all() and states.visited[STORED_PATH] == 600
    steps = stored_steps(WORLD, tiny_run, window=5)
    visited = {tuple(row) for row in np.round(steps.pose, 9)}
    assert all(tuple(row) in visited for row in np.round(states.world.pose, 9))
    # The fresh obstacles kept clear of the robot up to the labelled step.
    offset = states.world.obstacle_xy - states.world.pose[:, None, :2]
    gap = np.linalg.norm(offset, axis=-1).min(axis=1) - WORLD.obstacles.radius_m
    assert (gap > WORLD.robot_radius_m).all()
    target = encode_target(
        target_features(states.world.pose, states.world.target_xy), distance_scale_m(WORLD.lidar)
    )
    np.testing.assert_allclose(states.windows[:, -1], target)


def test_the_probe_fits_a_runs_redrawn_states(tiny_run: Path) -> None:
    settings = ProbeSettings(
        inputs="slots", epochs=2, batch_size=32, threads=1, redrawn_from=str(tiny_run)
    )
    fitted = probe(
        WORLD,
        replace(settings, redrawn_states=400),
        GaugeSettings(episodes_per_driver=6, max_episode_steps=40, num_worlds=6),
    )
    assert fitted.labelled_decisive > 0 and len(fitted.history) == 2


def test_a_run_of_another_world_or_a_network_seeing_scans_is_refused_by_name(
    tiny_run: Path,
) -> None:
    with pytest.raises(ConfigError, match=r"probe\.redrawn_from"):
        stored_steps(scenario("obstacles-increment"), tiny_run, window=5)
    with pytest.raises(ConfigError, match=r"probe\.redrawn_from"):
        ProbeSettings(redrawn_from=str(tiny_run))  # inputs = lidar
