import tomllib
from pathlib import Path

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import IncrementDynamics, InertiaDynamics
from qnav.contracts.observation import LidarSpec
from qnav.contracts.settings import field_docs, parse_assignments, to_toml, with_overrides
from qnav.sim.config import (
    SCENARIOS,
    ArenaConfig,
    ObstacleConfig,
    RewardConfig,
    SpawnConfig,
    WorldConfig,
    load_world,
)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_settings_written_as_toml_read_back_equal(name: str, tmp_path: Path) -> None:
    path = tmp_path / "world.toml"
    path.write_text(to_toml(SCENARIOS[name]))
    assert load_world("walls-inertia", path) == SCENARIOS[name]


def test_every_settings_field_is_documented() -> None:

    for cls in (
        WorldConfig,
        ArenaConfig,
        InertiaDynamics,
        IncrementDynamics,
        ObstacleConfig,
        SpawnConfig,
        RewardConfig,
        LidarSpec,
    ):
        docs = field_docs(cls)
        missing = [f for f in cls.__dataclass_fields__ if f not in docs]
        assert not missing, f"{cls.__name__} fields without a docstring: {missing}"


def test_unknown_setting_is_refused_by_its_full_name() -> None:
    with pytest.raises(ConfigError, match=r"unknown setting 'obstacles\.colour'"):
        with_overrides(SCENARIOS["walls-inertia"], {"obstacles": {"colour": "red"}})


def test_switching_dynamics_kind_replaces_the_whole_section() -> None:
    config = load_world("walls-inertia", None, ['dynamics.kind="increment"'])
    assert config.dynamics.kind == "increment"


def test_assignments_parse_values_as_toml() -> None:
    assert parse_assignments(["a.b=3", "a.c=0.5", 'd="x"', "e=true"]) == {
        "a": {"b": 3, "c": 0.5},
        "d": "x",
        "e": True,
    }


def test_wrong_type_names_setting_and_expected_type() -> None:
    with pytest.raises(ConfigError, match=r"obstacles\.count must be int"):
        load_world("walls-inertia", None, ['obstacles.count="many"'])


def test_toml_output_is_commented_with_field_docs() -> None:
    text = to_toml(SCENARIOS["obstacles-inertia"])
    assert "# Number of moving obstacles" in text
    assert tomllib.loads(text)["obstacles"]["count"] == 5
