"""The whole system as separate processes scores what the policy file scores in process.

Marked `stack` (about 6 minutes): `make test-stack`. It runs `qnav stack` (sim-car, controller,
bridge and recorder as their own processes on loopback, the car driven over MAVLink) for 50
test-protocol episodes and compares its success rate with `evaluate` of the same file on the
same episodes in process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from controller.policy import PolicyRuntime
from sim.config import scenario
from sim.evaluate import EvalSettings, StreamPolicyAgent, evaluate

# A small recurrent policy (LSTM 64) that reaches every target of walls-increment in about 20
# steps: `qnav train --scenario walls-increment --episodes 128 --seed 1 --train-set
# train.hidden_size=64`, then `qnav export RUN -o tests/data/stack/policy.onnx` (in the
# qnav-policy/1 layout; re-exported in /2 from its own weights with `qnav export FILE -o FILE`,
# metadata kept). A policy that often runs out of steps would cost 100 s of real time per
# unfinished episode.
POLICY = Path(__file__).parent / "data" / "stack" / "policy.onnx"
EPISODES = 50


@pytest.mark.stack
@pytest.mark.timeout(1200)
def test_the_full_stack_scores_within_five_hundredths_of_the_in_process_evaluation(
    tmp_path: Path,
) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "qnav", "stack", "--policy", str(POLICY), "--episodes",
         str(EPISODES), "--out", str(tmp_path / "stack"), "--json"],
        capture_output=True, text=True, timeout=1080, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    stack = json.loads(done.stdout.strip().splitlines()[-1])
    runtime = PolicyRuntime(POLICY, num_streams=EPISODES)
    world = scenario(runtime.contract.scenario)
    in_process = evaluate(
        world,
        StreamPolicyAgent(runtime, EPISODES),
        EvalSettings(episodes=EPISODES, num_worlds=EPISODES),
    )
    print(f"stack {stack['success']:.3f}, in process {in_process.success:.3f}")
    assert stack["episodes"] == EPISODES
    assert abs(stack["success"] - in_process.success) <= 0.05
    assert stack["exit_codes"]["controller"] == 0 and stack["exit_codes"]["bridge"] == 0
    assert stack["recording"], "the recorder wrote no MCAP file"


def test_the_stack_on_sitl_needs_a_binary_and_a_loopback_only_namespace(tmp_path: Path) -> None:
    # SITL serves unauthenticated TCP ports: `qnav stack --vehicle sitl` starts it only where
    # loopback is the only interface (make stack-sitl). Both refusals name what to do.
    from qnav.sitl import SITL_ENV, network_is_isolated

    base = [sys.executable, "-m", "qnav", "stack", "--vehicle", "sitl", "--policy", str(POLICY),
            "--out", str(tmp_path / "out")]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k != SITL_ENV}
    done = subprocess.run(base, capture_output=True, text=True, env=env, timeout=60, check=False)
    assert done.returncode == 2 and SITL_ENV in done.stderr
    if network_is_isolated():
        pytest.skip("this test runs in a loopback-only namespace: nothing to refuse")
    binary = tmp_path / "ardurover"
    binary.write_text("")
    done = subprocess.run(
        [*base, "--sitl-binary", str(binary)], capture_output=True, text=True, timeout=60,
        check=False,
    )  # fmt: skip
    assert done.returncode == 2 and "network namespace of its own" in done.stderr
    assert not (tmp_path / "out" / "sitl").exists(), "nothing was started"
