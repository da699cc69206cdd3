import pytest

from qnav.contracts.errors import ConfigError
from qnav.sim.config import load_world


@pytest.mark.parametrize(
    ("assignment", "setting"),
    [
        ("arena.size_m=-10", "arena.size_m"),
        ("robot_radius_m=-0.1", "robot_radius_m"),
        ("lidar.num_beams=0", "lidar.num_beams"),
        ("lidar.max_range_m=0", "lidar.max_range_m"),
        ("obstacles.count=500", "obstacles.count"),
        ("obstacles.radius_m=-1", "obstacles.radius_m"),
        ("obstacles.speed_min_mps=2.0", "obstacles.speed_max_mps"),
        ("control_period_s=0", "control_period_s"),
        ("max_episode_steps=0", "max_episode_steps"),
        ("spawn.wall_margin_m=0.1", "spawn.wall_margin_m"),
        ("spawn.target_max_distance_m=0.1", "spawn.target_max_distance_m"),
        ("dynamics.max_speed_mps=-1", "dynamics.max_speed_mps"),
    ],
)
def test_invalid_setting_is_refused_naming_the_setting_and_allowed_range(
    assignment: str, setting: str
) -> None:
    with pytest.raises(ConfigError) as error:
        load_world("obstacles-inertia", None, [assignment])
    message = str(error.value)
    assert message.startswith(setting), message
    assert "allowed" in message


def test_unknown_scenario_lists_the_known_ones() -> None:
    with pytest.raises(ConfigError, match=r"unknown scenario 'walls'.*walls-inertia"):
        load_world("walls")


def test_opening_wide_enough_for_the_robot_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"arena\.openings width_m"):
        load_world(
            "walls-inertia",
            None,
            ['arena.openings=[{wall="south", centre_m=5.0, width_m=1.5}]'],
        )


def test_opening_on_unknown_wall_is_refused() -> None:
    with pytest.raises(ConfigError, match="wall"):
        load_world(
            "walls-inertia", None, ['arena.openings=[{wall="up", centre_m=5.0, width_m=0.5}]']
        )
