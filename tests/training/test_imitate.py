"""The behaviour-cloning ceiling, run as a user runs it."""

import json
import subprocess
import sys

COMMAND = [
    sys.executable, "-m", "qnav", "imitate", "--scenario", "walls-increment",
    "--episodes", "48", "--held-out-episodes", "16", "--iterations", "150",
    "--test-episodes", "8", "--dagger-rounds", "1", "--dagger-episodes", "8",
    "--dodge-weight", "3",
    "--threads", "1", "--json",
]  # fmt: skip


def test_imitate_clones_the_planner_and_prints_json() -> None:
    done = subprocess.run(COMMAND, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["planner_success"] == 1.0  # walls only: the planner reaches every target
    assert result["windows"] > 48
    assert result["test"]["episodes"] == 8
    # Copying works: most of the planner's decisions, seen or not, are the clone's too.
    assert result["train_agreement"] > 0.8
    assert result["held_out_agreement"] > 0.7
    # Even without obstacles the planner turns where go-to-target would not (it plans the
    # turns' timing), so there are dodges, and the clone's choices on them are counted.
    assert 0.0 < result["dodge_share"] < 0.5
    # On a dodge the clone cannot pick both the planner's action and go-to-target's: the two
    # shares of the same count sum to at most 1 (up to float rounding, not a margin).
    assert result["dodge_as_baseline"] >= 0.0
    assert result["dodge_as_baseline"] + result["dodge_agreement"] <= 1.0 + 1e-9
    # DAgger: the first copy, then one round that added the copy's own states, labelled.
    first, second = result["dagger"]
    assert (first["round"], second["round"]) == (0, 1)
    assert first["windows"] == result["windows"] < second["windows"]
