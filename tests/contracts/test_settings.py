import re
import tomllib
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.motion import IncrementDynamics, InertiaDynamics
from qnav.contracts.observation import LidarSpec
from qnav.contracts.settings import (
    field_docs,
    from_dict,
    parse_assignments,
    to_toml,
    with_overrides,
)
from qnav.controller.config import DaemonConfig, load_config
from qnav.firmware_bridge.settings import BridgeSettings
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


@pytest.mark.parametrize(
    ("cls", "values", "named", "expected"),
    [
        (DaemonConfig, {"safety": {"scan_timeout_s": True}}, "safety.scan_timeout_s", "float"),
        (WorldConfig, {"obstacles": {"count": False}}, "obstacles.count", "int"),
        (BridgeSettings, {"mavlink": {"connection": True}}, "mavlink.connection", "str"),
        (BridgeSettings, {"vision": {"max_position_m": True}}, "vision.max_position_m", "float"),
    ],
)
def test_a_boolean_is_no_number_or_text_for_any_setting(
    cls: type, values: dict[str, Any], named: str, expected: str
) -> None:
    # TOML's `true` used to become 1.0, 1 or "True" (issue 53).
    message = rf"{re.escape(named)} must be {expected}, got (True|False)"
    with pytest.raises(ConfigError, match=message):
        from_dict(cls, values)


def test_a_boolean_for_a_number_is_refused_from_a_file_and_from_set(tmp_path: Path) -> None:
    path = tmp_path / "controller.toml"
    path.write_text("[safety]\nscan_timeout_s = true\n")
    with pytest.raises(ConfigError, match=r"safety\.scan_timeout_s must be float, got True"):
        load_config(path)
    with pytest.raises(ConfigError, match=r"safety\.scan_timeout_s must be float, got True"):
        load_config(None, ["safety.scan_timeout_s=true"])
