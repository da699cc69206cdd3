"""The sim-car's settings against its world."""

from __future__ import annotations

from dataclasses import replace

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.transport import ZenohSettings
from qnav.sim.config import scenario
from qnav.simcar.car import SimCar, SimCarSettings


def test_a_rotating_lidar_needs_the_sim_car_in_lockstep() -> None:
    # Only in lockstep does the sim-car move the car itself and so know its path within a turn.
    world = replace(scenario("obstacles-inertia"), lidar_turn_s=0.1)
    with pytest.raises(ConfigError, match=r"lidar_turn_s needs the sim-car in lockstep"):
        SimCar(world, SimCarSettings(), ZenohSettings())
