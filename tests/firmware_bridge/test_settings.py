"""Bridge settings: the example file is complete, wrong values are refused by name."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import pytest

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import from_dict, to_dict, to_markdown
from qnav.firmware_bridge.core import EXIT_ACK_WAIT_S, EXIT_DISARM_TRIES
from qnav.firmware_bridge.settings import BridgeSettings, FailsafeSettings, load_settings

ROOT = Path(__file__).resolve().parents[2]


def test_print_config_sets_every_setting_to_its_default() -> None:
    settings = load_settings(ROOT / "config" / "bridge.toml")
    assert settings == BridgeSettings()
    # Every field appears in the example file, so it documents them all.
    text = (ROOT / "config" / "bridge.toml").read_text()
    for section in dataclasses.fields(BridgeSettings):
        for item in dataclasses.fields(getattr(settings, section.name)):
            if item.name not in ("config_file", "extra"):
                assert f"\n{item.name} =" in text, f"{section.name}.{item.name} missing"


@pytest.mark.parametrize(
    ("values", "named"),
    [
        ({"failsafe": {"command_timeout_s": -1.0}}, "failsafe.command_timeout_s"),
        ({"failsafe": {"stop_period_s": 0.0}}, "failsafe.stop_period_s"),
        ({"mavlink": {"gcs_system_id": 0}}, "mavlink.gcs_system_id"),
        ({"mavlink": {"connection": "bluetooth:car"}}, "mavlink.connection"),
        ({"output": {"mode": "auto"}}, "output.mode"),
        ({"output": {"throttle_pwm_max_us": 1400}}, "output.throttle_pwm_max_us"),
        ({"output": {"steering_pwm_trim_us": 1000}}, "output.steering_pwm_trim_us"),
        ({"output": {"speed_at_full_throttle_mps": 0.0}}, "output.speed_at_full_throttle_mps"),
        ({"signing": {"enabled": True}}, "signing.key_file"),
        ({"signing": {"enabled": True, "key_file": "/nonexistent"}}, "signing.key_file"),
        ({"failsafe": {"timeout": 1.0}}, "failsafe.timeout"),
    ],
)
def test_wrong_setting_is_refused_with_its_name(values: dict[str, Any], named: str) -> None:
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        from_dict(BridgeSettings, values)


def test_settings_survive_a_round_trip_through_a_dict() -> None:
    settings = from_dict(BridgeSettings, {"output": {"mode": "guided"}})
    assert from_dict(BridgeSettings, to_dict(settings)) == settings
    assert settings.rover_mode == 15


def test_settings_table_in_the_docs_is_current() -> None:
    table = to_markdown(BridgeSettings())
    assert table in (ROOT / "docs" / "bridge.md").read_text(), (
        "paste `to_markdown(BridgeSettings())` into docs/bridge.md"
    )


def test_the_service_managers_let_the_bridge_brake_to_rest_before_they_kill_it() -> None:
    # On exit the bridge may brake for failsafe.brake_timeout_s before it disarms (issue 53); a
    # SIGKILL before that leaves the car to the autopilot's own failsafe, armed.
    longest_s = FailsafeSettings().brake_timeout_s + EXIT_DISARM_TRIES * EXIT_ACK_WAIT_S + 1.0
    unit = (ROOT / "deploy" / "systemd" / "qnav-bridge.service").read_text()
    (systemd,) = re.findall(r"^TimeoutStopSec=(\d+)$", unit, re.MULTILINE)
    compose = (ROOT / "deploy" / "compose.yaml").read_text()
    bridge = compose[compose.index("  bridge:") :]
    docker = re.search(r"stop_grace_period: (\d+)s", bridge)
    assert docker is not None
    assert int(systemd) >= longest_s and int(docker[1]) >= longest_s
