"""The full stack on the firmware: policy -> controller -> bridge -> ArduPilot Rover SITL.

`qnav stack --vehicle sitl` as a user runs it (its own processes: ardurover, sim-car,
controller, bridge), two walls-only episodes: the robot's pose is the autopilot's own
LOCAL_POSITION_NED and ATTITUDE, the walls and lidar are simulated around it. The committed
stack policy reaches the target of both episodes in process; on the firmware it must too.
The 20-episode figure: `make stack-sitl` (docs/bridge-testing.md, "The full stack on the firmware").
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from qnav.sitl import SITL_ENV, network_is_isolated

pytestmark = pytest.mark.sitl

ROOT = Path(__file__).resolve().parents[2]
POLICY = ROOT / "tests" / "data" / "stack" / "policy.onnx"
EPISODES = 2


@pytest.mark.timeout(600)
def test_the_policy_drives_the_firmware_to_its_targets(tmp_path: Path) -> None:
    if not network_is_isolated():
        pytest.skip(
            "qnav stack --vehicle sitl runs only in a loopback-only namespace (make test-sitl)"
        )
    done = subprocess.run(
        [sys.executable, "-m", "qnav", "stack", "--vehicle", "sitl",
         "--sitl-binary", os.environ[SITL_ENV], "--policy", str(POLICY),
         "--episodes", str(EPISODES), "--no-record", "--out", str(tmp_path / "stack"), "--json"],
        capture_output=True, text=True, timeout=540, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    print(f"\n[sitl] stack on SITL: {result['outcomes']}, in process: {result['in_process']}")
    assert result["vehicle"] == "sitl"
    assert result["episodes"] == EPISODES
    assert result["in_process"]["success"] == 1.0, "the committed policy changed"
    assert result["outcomes"] == ["success"] * EPISODES
    assert result["exit_codes"]["controller"] == 0 and result["exit_codes"]["bridge"] == 0
    # The robot moved as the autopilot moved: each episode's poses are the firmware's.
    episodes = [
        json.loads(line)
        for line in (tmp_path / "stack" / "episodes.jsonl").read_text().splitlines()
    ]
    for episode in episodes:
        start, end = episode["poses"][0], episode["poses"][-1]
        assert abs(end[0] - start[0]) + abs(end[1] - start[1]) > 1.0
