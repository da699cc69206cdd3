"""`qnav bench controller`: three processes, one command per scan, the documented JSON."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import PolicyFactory

ROOT = Path(__file__).resolve().parents[2]


def _qnav_json(*args: str) -> dict[str, Any]:
    """Run `qnav ARGS` as a user would and parse the JSON it prints."""
    done = subprocess.run(
        [str(Path(sys.executable).parent / "qnav"), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    report: dict[str, Any] = json.loads(done.stdout)
    return report


def test_bench_controller_times_one_command_per_published_scan_and_prints_json(
    make_policy: PolicyFactory,
) -> None:
    policy = make_policy("walls-inertia")
    report = _qnav_json(
        *("bench", "controller", "--policy", str(policy)),
        *("--rates", "20,50", "--seconds", "0.5", "--json"),
    )
    assert [r["rate_hz"] for r in report["results"]] == [20.0, 50.0]
    for result in report["results"]:
        assert result["commands"] == result["scans"]  # a decision for every scan, none lost
        assert 0 < result["p50_ms"] <= result["p99_ms"] <= result["max_ms"]
        parts = [result[f"{part}_p50_ms"] for part in ("inbound", "daemon", "outbound")]
        assert all(0 < part < result["p50_ms"] for part in parts), parts


def test_bench_controller_with_the_shield_times_its_decisions_on_a_drive_through_the_room() -> None:
    policy = ROOT / "tests" / "data" / "stack" / "obstacles-inertia.onnx"
    report = _qnav_json(
        *("bench", "controller", "--policy", str(policy), "--lookahead", "shield", "--cpu", "0"),
        *("--rates", "5", "--seconds", "2", "--json"),
    )
    assert report["lookahead"] == "shield" and report["daemon_cpu"] == 0
    (result,) = report["results"]
    # Every scan of the drive gets its decision (the car reaches no target within 2 s).
    assert result["commands"] == result["scans"] == 10
    assert 0 < result["daemon_p50_ms"] <= result["daemon_p99_ms"] <= result["max_ms"]


def test_bench_policy_times_each_backend_after_the_given_gap_and_prints_json(
    make_policy: PolicyFactory,
) -> None:
    policy = make_policy("walls-inertia")
    report = _qnav_json(
        *("bench", "policy", "--policy", str(policy), "--decisions", "20"),
        *("--gap-ms", "2", "--json"),
    )
    assert report["gap_ms"] == 2.0
    assert set(report["backends"]) == {"onnxruntime", "numpy"}
    for stats in report["backends"].values():
        assert stats["decisions"] == 20 and stats["gap_ms"] == 2.0
        assert 0 < stats["p50_ms"] <= stats["p99_ms"] <= stats["max_ms"]


def test_bench_policy_refuses_a_negative_gap_naming_the_option() -> None:
    from qnav.contracts.errors import ConfigError
    from qnav.controller.bench import run

    with pytest.raises(ConfigError, match="--gap-ms"):
        run(Path("unused.onnx"), ["numpy"], 10, gap_s=-0.001)


def test_bench_policy_times_the_paper_sized_policy_in_the_weight_type_asked_for() -> None:
    report = _qnav_json(
        *("bench", "policy", "--weights", "int8", "--backends", "onnxruntime"),
        *("--decisions", "20", "--json"),
    )
    assert report["policy"].endswith("int8 weights")
    assert report["backends"]["onnxruntime"]["decisions"] == 20


def test_bench_weights_and_policy_are_exclusive(make_policy: PolicyFactory) -> None:
    from qnav.cli import main as qnav

    with pytest.raises(SystemExit) as refused:
        qnav(["bench", "policy", "--policy", str(make_policy()), "--weights", "int8"])
    assert refused.value.code == 2
