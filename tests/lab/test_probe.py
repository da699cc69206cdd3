"""The perception probe: a supervised fit to doom labels, judged on the held-out gauge."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from qnav.contracts.errors import ConfigError
from qnav.contracts.observation import distance_scale_m
from qnav.lab.decisive import GaugeSettings, collect
from qnav.lab.oracle import PERCEIVED
from qnav.lab.probe import (
    PerceptionSettings,
    Probe,
    ProbeSettings,
    decisive_only,
    fitted_labels,
    perceive,
    perception_windows,
    probe,
    shield_test,
    state_features,
)
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings
from qnav.sim.world import reset
from tests.command import run_qnav

SMALL_GAUGE = GaugeSettings(episodes_per_driver=6, max_episode_steps=40, num_worlds=6)
SMALL = ProbeSettings(episodes_per_driver=6, epochs=2, batch_size=32, threads=1)


def test_an_ordinary_share_keeps_states_where_all_or_no_actions_are_doomed() -> None:
    world = scenario("obstacles-increment")
    only = collect(world, SMALL_GAUGE)
    some = collect(world, replace(SMALL_GAUGE, ordinary_share=0.5))
    assert len(some.doomed) > len(only.doomed)
    assert len(decisive_only(some).doomed) == len(only.doomed)
    np.testing.assert_array_equal(decisive_only(some).windows, only.windows)


def test_each_pass_reports_its_fit_and_the_held_out_gauge() -> None:
    fitted = probe(scenario("obstacles-increment"), SMALL, SMALL_GAUGE)
    labelled = collect(scenario("obstacles-increment"), SMALL.labelled_set(SMALL_GAUGE))
    assert fitted.labelled_states == len(labelled.doomed)
    assert fitted.labelled_decisive == len(decisive_only(labelled).doomed) > 0
    assert fitted.held_out_decisive > 0
    history = fitted.history
    assert [epoch.epoch for epoch in history] == [1, 2]
    for epoch in history:
        assert np.isfinite(epoch.loss) and epoch.loss > 0
        assert 0.0 <= epoch.safe <= 1.0 and 0.0 <= epoch.balanced <= 1.0


@pytest.mark.parametrize(
    ("inputs", "label"),
    [("state", "doom"), ("lidar", "collide_share"), ("state", "collide_share"), ("slots", "doom")],
)
def test_the_probe_fits_exact_state_and_graded_labels_too(inputs: str, label: str) -> None:
    settings = replace(SMALL, inputs=inputs, label=label)  # type: ignore[arg-type]
    history = probe(scenario("obstacles-increment"), settings, SMALL_GAUGE).history
    assert len(history) == 2
    assert all(np.isfinite(epoch.loss) and 0.0 <= epoch.balanced <= 1.0 for epoch in history)


def test_one_label_per_state_is_the_taken_or_a_random_actions() -> None:
    share = np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.25]] * 500, dtype=np.float32)
    taken = np.tile([0, 2], 500)
    target, seen = fitted_labels(share, replace(SMALL, labelled_actions="taken"), taken)
    np.testing.assert_array_equal(target, 1.0 - (share == 1.0))
    np.testing.assert_array_equal(seen.argmax(axis=1), taken)
    assert (seen.sum(axis=1) == 1).all()
    _, seen = fitted_labels(share, replace(SMALL, labelled_actions="random"))
    assert (seen.sum(axis=1) == 1).all()
    assert np.bincount(seen.argmax(axis=1), minlength=3).min() > 250  # about a third each
    _, seen = fitted_labels(share, SMALL)
    assert (seen == 1).all()
    with pytest.raises(ConfigError, match="labelled_actions"):
        fitted_labels(share, replace(SMALL, labelled_actions="taken"))


def test_an_outcome_label_is_one_continuation_drawn_by_the_collision_share() -> None:
    share = np.array([[1.0, 0.25, 0.0]] * 4000, dtype=np.float32)
    target, _ = fitted_labels(share, replace(SMALL, label="outcome"))
    assert set(np.unique(target)) <= {0.0, 1.0}
    assert (target[:, 0] == 0).all() and (target[:, 2] == 1).all()
    assert target[:, 1].mean() == pytest.approx(0.75, abs=0.03)


@pytest.mark.parametrize("labelled_actions", ["taken", "random"])
def test_the_probe_fits_one_label_per_state(labelled_actions: str) -> None:
    settings = replace(SMALL, inputs="slots", labelled_actions=labelled_actions)  # type: ignore[arg-type]
    history = probe(scenario("obstacles-increment"), settings, SMALL_GAUGE).history
    assert len(history) == 2
    assert all(np.isfinite(epoch.loss) and 0.0 <= epoch.balanced <= 1.0 for epoch in history)


class _TrustsEveryAction(torch.nn.Module):
    def forward(self, context: torch.Tensor, obstacles: torch.Tensor) -> torch.Tensor:
        return torch.full((len(context), 3), 10.0)


SMALL_PROTOCOL = EvalSettings(episodes=12, max_episode_steps=60)


def test_a_shield_that_trusts_every_action_is_go_to_target_alone() -> None:
    world = scenario("obstacles-inertia")
    settings = replace(SMALL, inputs="slots", shield_episodes=SMALL_PROTOCOL.episodes)
    test = shield_test(world, Probe([], _TrustsEveryAction()), settings, SMALL_PROTOCOL)
    assert test.fitted == test.blind and test.fitted_overruled == 0.0
    assert test.blind.episodes == test.exact.episodes == SMALL_PROTOCOL.episodes
    # The exact labels overrule go-to-target only where its action is doomed: seldom.
    assert 0.0 < test.exact_overruled < 0.5


def test_a_fitted_network_shields_go_to_target_from_the_state_it_judges() -> None:
    world = scenario("obstacles-increment")
    for inputs in ("state", "slots"):
        settings = replace(SMALL, inputs=inputs, shield_episodes=SMALL_PROTOCOL.episodes)
        test = shield_test(world, probe(world, settings, SMALL_GAUGE), settings, SMALL_PROTOCOL)
        results = [test.blind, test.fitted, test.exact]
        # A car perceives the obstacles through its tracker: slot inputs are tested on it too.
        assert (test.tracked is not None) == (inputs == "slots")
        results += [test.tracked] if test.tracked is not None else []
        for result in results:
            assert result.episodes == SMALL_PROTOCOL.episodes
            assert result.success + result.collision + result.unfinished == pytest.approx(1.0)
        assert 0.0 <= test.fitted_overruled <= 1.0 and 0.0 <= test.tracked_overruled <= 1.0


def test_state_features_are_in_the_robots_frame() -> None:
    world = scenario("obstacles-increment")
    state = reset(world, np.zeros(1, np.int64), np.zeros(1, np.int64))
    heading = state.pose[0, 2]
    ahead = state.pose[0, :2] + 1.0 * np.array([np.cos(heading), np.sin(heading)])
    state = state._replace(obstacle_xy=np.tile(ahead, (1, world.obstacles.count, 1)))
    context, obstacles = state_features(state, world.arena.size_m)
    half = world.arena.size_m / 2
    assert context.shape == (1, 8) and obstacles.shape == (1, world.obstacles.count, 7)
    np.testing.assert_allclose(
        obstacles[0, :, :2], [[1.0 / half, 0.0]] * world.obstacles.count, atol=1e-6
    )
    np.testing.assert_allclose(obstacles[0, :, 4], 1.0 / half, rtol=1e-6)


def test_a_wrong_probe_setting_names_itself() -> None:
    with pytest.raises(ConfigError, match="epochs"):
        ProbeSettings(epochs=0)
    result = run_qnav("lab", "probe", "--probe-set", "probe.learning_rate=0", "--json")
    assert result.returncode != 0
    assert "learning_rate" in result.stderr
    result = run_qnav("lab", "probe", "--probe-set", "probe.inputs=radar", "--json")
    assert result.returncode != 0
    assert "probe.inputs" in result.stderr
    with pytest.raises(ConfigError, match=r"probe\.shield_episodes"):
        ProbeSettings(inputs="lidar", shield_episodes=10)
    result = run_qnav("lab", "probe", "--probe-set", "probe.labelled_actions=one", "--json")
    assert result.returncode != 0
    assert "probe.labelled_actions" in result.stderr


def test_qnav_probe_prints_its_settings() -> None:
    result = run_qnav("lab", "probe", "--print-config")
    assert result.returncode == 0, result.stderr
    assert "ordinary_share" in result.stdout


SMALL_PERCEPTION = PerceptionSettings(
    windows=300, held_out_windows=100, epochs=2, batch_size=64, threads=1
)


def test_perception_windows_label_the_nearest_obstacle_within_reach() -> None:
    world = scenario("obstacles-inertia")
    windows, truth = perception_windows(world, 50, SMALL_PERCEPTION, seed=1)
    assert windows.shape == (50, 5, 723) and truth.shape == (50, len(PERCEIVED))
    ahead, left = truth[:, 0], truth[:, 1]
    assert (np.hypot(ahead, left) <= SMALL_PERCEPTION.max_distance_m + 1e-5).all()
    # The newest scan sees that obstacle's near surface, or something nearer in front of it.
    max_range_m = distance_scale_m(world.lidar)
    nearest_return_m = windows[:, -1, :-3].astype(np.float64).min(axis=1) * max_range_m
    assert (nearest_return_m <= np.hypot(ahead, left) - world.obstacles.radius_m + 0.05).all()


def test_the_perception_probe_reports_the_blind_baseline_then_each_pass() -> None:
    history = perceive(scenario("obstacles-inertia"), SMALL_PERCEPTION)
    assert [epoch.epoch for epoch in history] == [0, 1, 2]
    for epoch in history:
        assert set(epoch.errors) == set(PERCEIVED)
        assert all(np.isfinite(value) and value >= 0 for value in epoch.errors.values())


def test_qnav_probe_perception_names_its_settings() -> None:
    result = run_qnav("lab", "probe", "--perception", "--print-config")
    assert result.returncode == 0, result.stderr
    assert "conv_channels" in result.stdout
    result = run_qnav("lab", "probe", "--perception", "--probe-set", "perception.windows=0")
    assert result.returncode != 0
    assert "perception.windows" in result.stderr
