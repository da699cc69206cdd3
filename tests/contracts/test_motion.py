import math

import numpy as np
import pytest

from qnav.contracts.actions import Action
from qnav.contracts.motion import (
    IncrementDynamics,
    InertiaDynamics,
    move_obstacles,
    step_increment,
    step_inertia,
)

START = np.array([[5.0, 5.0, 0.0]])
REST = np.zeros((1, 2))


def _act(action: Action) -> np.ndarray:
    return np.array([int(action)])


def test_increment_forward_moves_exactly_one_step_along_heading() -> None:
    pose, _ = step_increment(START, REST, _act(Action.FORWARD), IncrementDynamics())
    np.testing.assert_allclose(pose, [[5.2, 5.0, 0.0]])


@pytest.mark.parametrize(("action", "sign"), [(Action.LEFT, 1.0), (Action.RIGHT, -1.0)])
def test_increment_turn_rotates_in_place(action: Action, sign: float) -> None:
    pose, _ = step_increment(START, REST, _act(action), IncrementDynamics())
    np.testing.assert_allclose(pose, [[5.0, 5.0, sign * 0.2]])


def test_inertia_speed_settles_at_the_maximum_under_forward() -> None:
    params = InertiaDynamics()
    pose, velocity = START, REST
    for _ in range(50):
        pose, velocity = step_inertia(pose, velocity, _act(Action.FORWARD), params, 0.2)
    assert velocity[0, 0] == pytest.approx(params.max_speed_mps, rel=1e-6)
    # Ten seconds at a speed rising as 1 - exp(-t / tau): x = v (t - tau (1 - exp(-t / tau))).
    tau = params.linear_time_constant_s
    expected = 5.0 + params.max_speed_mps * (10.0 - tau * (1 - math.exp(-10.0 / tau)))
    assert pose[0, 0] == pytest.approx(expected, rel=1e-9)


def test_inertia_turn_from_rest_rotates_in_place_towards_the_maximum_rate() -> None:
    params = InertiaDynamics()
    pose, velocity = step_inertia(START, REST, _act(Action.LEFT), params, 0.2)
    np.testing.assert_allclose(pose[0, :2], START[0, :2])
    assert 0 < velocity[0, 1] < params.max_turn_rate_radps
    assert pose[0, 2] > 0


def test_inertia_keeps_momentum_after_forward_stops() -> None:
    params = InertiaDynamics()
    moving = np.array([[0.5, 0.0]])
    pose, velocity = step_inertia(START, moving, _act(Action.LEFT), params, 0.2)
    assert pose[0, 0] > 5.0  # it coasts while turning
    assert 0 < velocity[0, 0] < 0.5


def test_obstacles_bounce_off_walls_and_keep_their_speed() -> None:
    position = np.array([[[0.5, 5.0]]])
    velocity = np.array([[[-1.5, 0.3]]])
    moved, new_velocity = move_obstacles(position, velocity, 0.4, 10.0, 0.2)
    assert moved[0, 0, 0] == pytest.approx(0.4 + (0.3 - 0.1))
    np.testing.assert_allclose(new_velocity, [[[1.5, 0.3]]])
