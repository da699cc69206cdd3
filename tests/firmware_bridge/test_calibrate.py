"""`qnav calibrate-car`: the fit, and the pattern driven through a real bridge to the test car."""

from __future__ import annotations

import tomllib
from collections.abc import Callable
from pathlib import Path

import pytest

from qnav.contracts.settings import from_dict
from qnav.firmware_bridge.calibrate import (
    CalibrationAbortedError,
    Calibrator,
    Pattern,
    fit_through_origin,
    output_section,
    with_scales,
)
from qnav.firmware_bridge.settings import BridgeSettings
from tests.command import run_qnav
from tests.firmware_bridge.rig import Rig, wait_until

ROOT = Path(__file__).resolve().parents[2]

MakeRig = Callable[..., Rig]


def test_the_fit_is_a_line_through_the_origin() -> None:
    assert fit_through_origin([0.2, 0.4], [0.4, 0.8]) == pytest.approx(2.0)
    assert fit_through_origin([0.3, -0.3], [0.45, -0.45]) == pytest.approx(1.5)
    with pytest.raises(ValueError):
        fit_through_origin([0.0], [1.0])
    assert "speed_at_full_throttle_mps = 2.000" in output_section(2.0, 1.5)


def test_calibration_finds_the_cars_full_throttle_speed_and_turn_rate(make_rig: MakeRig) -> None:
    # The bridge believes full throttle is 1 m/s; the car does 2 m/s and 1.5 rad/s.
    rig = make_rig(
        vehicle={"dynamics": {"max_speed_mps": 2.0, "max_turn_rate_radps": 1.5}},
        bridge={"output": {"speed_at_full_throttle_mps": 1.0}},
    )
    rig.ready()
    assert rig.bridge is not None
    pattern = Pattern(settle_s=0.6, measure_s=0.6, rest_timeout_s=5.0, max_distance_m=50.0)
    calibrator = Calibrator(rig.bridge.settings, pattern)
    try:
        calibrator.wait_ready(10.0)
        result = calibrator.calibrate()
    finally:
        calibrator.close()
    assert result["speed_at_full_throttle_mps"] == pytest.approx(2.0, rel=0.1)
    assert result["turn_rate_at_full_steering_radps"] == pytest.approx(1.5, rel=0.1)
    assert len(result["runs"]) == 3 + 4


def test_calibration_aborts_beyond_its_distance_bound_and_the_bridge_stops_the_car(
    make_rig: MakeRig,
) -> None:
    rig = make_rig()
    rig.ready()
    assert rig.bridge is not None
    pattern = Pattern(settle_s=1.0, measure_s=1.0, max_distance_m=0.1)
    calibrator = Calibrator(rig.bridge.settings, pattern)
    try:
        calibrator.wait_ready(10.0)
        with pytest.raises(CalibrationAbortedError, match="beyond max_distance_m"):
            calibrator.calibrate()
    finally:
        calibrator.close()
    travelled = rig.vehicle.pose()[0]
    assert 0.1 < travelled < 0.5
    wait_until(lambda: abs(rig.vehicle.velocity()[0]) < 0.02, what="the failsafe stop")


def _settings(text: str) -> BridgeSettings:
    return from_dict(BridgeSettings, tomllib.loads(text))


def test_the_scales_are_written_into_the_bridges_file_and_nothing_else_changes() -> None:
    shipped = (ROOT / "config" / "bridge.toml").read_text()
    assert _settings(shipped).output.speed_at_full_throttle_mps is None  # not measured
    written = with_scales(shipped, 2.4567, 1.25)
    settings = _settings(written)
    assert settings.output.speed_at_full_throttle_mps == 2.457
    assert settings.output.turn_rate_at_full_steering_radps == 1.25
    # Every other line, comments included, as it was.
    changed = [
        (a, b) for a, b in zip(shipped.splitlines(), written.splitlines(), strict=True) if a != b
    ]
    assert [b for _, b in changed] == [
        "speed_at_full_throttle_mps = 2.457",
        "turn_rate_at_full_steering_radps = 1.250",
    ]


@pytest.mark.parametrize(
    "text",
    [
        '[zenoh]\nnamespace = "car1"\n',
        '[output]\nmode = "manual"\n\n[failsafe]\ncommand_timeout_s = 0.4\n',
        "",
    ],
)
def test_scales_missing_from_the_file_are_added_to_its_output_section(text: str) -> None:
    settings = _settings(with_scales(text, 3.0, 2.0))
    assert settings.output.speed_at_full_throttle_mps == 3.0
    assert settings.output.turn_rate_at_full_steering_radps == 2.0
    before = _settings(text)
    assert settings.zenoh == before.zenoh and settings.failsafe == before.failsafe


def test_calibrate_car_write_needs_the_file_to_write_into() -> None:
    refused = run_qnav("calibrate-car", "--write")
    assert refused.returncode == 2
    assert "--write" in refused.stderr and "--config" in refused.stderr
