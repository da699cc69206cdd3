"""`qnav bridge` and `qnav bench bridge` as a user runs them: real processes, real signals."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path

import pytest

from qnav.contracts.health import HEALTH_FILE_ENV
from qnav.contracts.mavlink import MAV_CMD_COMPONENT_ARM_DISARM
from qnav.contracts.settings import to_toml
from tests.command import run_qnav
from tests.firmware_bridge.rig import bridge_settings, start_rig, wait_until


@pytest.mark.parametrize("stop_signal", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_bridge_process_sends_stop_then_disarms_on_a_signal(
    tmp_path: Path, stop_signal: signal.Signals
) -> None:
    with ExitStack() as stack:
        rig = start_rig(stack, start_bridge=False)
        config = tmp_path / "bridge.toml"
        config.write_text(to_toml(bridge_settings(rig.zenoh_port, rig.mavlink_port)))
        health = tmp_path / "health.json"
        process = subprocess.Popen(
            [sys.executable, "-m", "qnav", "bridge", "--config", str(config)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, HEALTH_FILE_ENV: str(health)},
        )
        try:
            wait_until(lambda: rig.state().get("armed"), timeout_s=20, what="bridge up, armed")
            # Drive until the car has moved (a deadline, not a fixed 0.3 s: a loaded machine
            # may take longer to carry the first commands through).
            wait_until(
                lambda: rig.drive(0.8, 0.0, 0.05) and rig.vehicle.pose()[0] > 0.01,
                timeout_s=20,
                what="the car moving on the bridge's commands",
            )
            wait_until(lambda: "link_up=True" in qnav_health(health), 20, "a healthy beat")
            process.send_signal(stop_signal)
            rig.drive(0.8, 0.0, 0.1)  # commands racing the shutdown must not get through
            output, _ = process.communicate(timeout=20)
        finally:
            if process.poll() is None:
                process.kill()
        assert process.returncode == 0, output
        assert "Traceback" not in output
        received = rig.vehicle.received(["RC_CHANNELS_OVERRIDE", "COMMAND_LONG"])
        disarm = next(
            i
            for i, r in enumerate(received)
            if r.type == "COMMAND_LONG"
            and r.fields["command"] == MAV_CMD_COMPONENT_ARM_DISARM
            and r.fields["param1"] == 0.0
        )
        overrides = [r for r in received[:disarm] if r.type == "RC_CHANNELS_OVERRIDE"]
        last_moving = max(
            i
            for i, r in enumerate(overrides)
            if (r.fields["chan1_raw"], r.fields["chan3_raw"]) != (1500, 1500)
        )
        assert len(overrides) - last_moving - 1 >= 3, "stop sent (three times) before disarm"
        assert all(r.type == "COMMAND_LONG" for r in received[disarm:])
        assert not rig.vehicle.armed
        assert qnav_health(health).startswith("unhealthy: no health file")


def qnav_health(path: Path) -> str:
    """What `qnav health --file path` prints, as a container's HEALTHCHECK runs it."""
    done = run_qnav("health", "--file", str(path))
    assert done.returncode == (0 if done.stdout.startswith("healthy") else 1), done
    return done.stdout


def test_bridge_refuses_a_bad_setting_with_its_name(tmp_path: Path) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text("[failsafe]\ncommand_timeout_s = -1.0\n")
    result = run_qnav("bridge", "--config", str(config))
    assert result.returncode == 2
    assert "failsafe.command_timeout_s = -1.0 is out of range" in result.stderr
    assert "Traceback" not in result.stderr


def test_bridge_refuses_a_port_it_cannot_open() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        result = run_qnav("bridge", "--set", f'mavlink.connection="udpin:127.0.0.1:{port}"')
    assert result.returncode == 2
    assert "mavlink.connection" in result.stderr and "cannot be opened" in result.stderr


def test_bench_bridge_json_has_the_documented_figures() -> None:
    result = run_qnav(
        "bench", "bridge", "--commands", "30", "--stops", "1", "--timeout-s", "0.1", "--json"
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert set(report) == {"p50_ms", "p99_ms", "failsafe_stop_ms"}
    assert 0 < report["p50_ms"] <= report["p99_ms"]
    assert report["failsafe_stop_ms"] >= 100


@pytest.mark.parametrize("verb", [["bridge"], ["fake-vehicle"], ["bench", "bridge"]])
def test_bridge_verbs_have_help(verb: list[str]) -> None:
    result = run_qnav(*verb, "--help")
    assert result.returncode == 0 and "usage: qnav" in result.stdout
