"""The behaviour-cloning ceiling, run as a user runs it."""

import json
import subprocess
import sys
from fractions import Fraction
from typing import Any

import pytest

COMMAND = [sys.executable, "-m", "qnav", "lab", "imitate", "--scenario", "walls-increment"]
FULL = [
    "--episodes", "48", "--held-out-episodes", "16", "--iterations", "150",
    "--test-episodes", "8", "--dagger-rounds", "1", "--dagger-episodes", "8",
    "--dodge-weight", "3", "--threads", "1", "--json",
]  # fmt: skip
SLICE = [
    "--episodes", "8", "--held-out-episodes", "4", "--iterations", "10",
    "--test-episodes", "2", "--dagger-rounds", "1", "--dagger-episodes", "2",
    "--dodge-weight", "3", "--threads", "1", "--json",
]  # fmt: skip
"""A short seeded slice of `FULL` for the default suite: the same verb, too few steps to learn."""


def _ratio(fraction: float) -> Fraction:
    """The ratio of counts a reported fraction was computed from (counts up to a million: two
    such ratios differ by far more than a float's rounding). In floats, 1 - 0.9 is
    0.09999999999999998 and 0.9 + 0.1 of the same 10 cases compare wrongly; as counts they
    do not."""
    return Fraction(fraction).limit_denominator(10**6)


def _imitate(arguments: list[str]) -> dict[str, Any]:
    done = subprocess.run(
        [*COMMAND, *arguments], capture_output=True, text=True, timeout=600, check=False
    )
    assert done.returncode == 0, done.stderr
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def _check_the_report(result: dict[str, Any], episodes: int, test_episodes: int) -> None:
    """What holds on every run, learnt or not."""
    assert result["planner_success"] == 1.0  # walls only: the planner reaches every target
    assert result["windows"] > episodes
    assert result["test"]["episodes"] == test_episodes
    # On a dodge the planner's action is not go-to-target's, so the clone cannot pick both.
    # Compared as counts: each fraction back to the ratio of integers it was computed from.
    as_baseline, agreement = (_ratio(result[k]) for k in ("dodge_as_baseline", "dodge_agreement"))
    assert as_baseline >= 0 and as_baseline + agreement <= 1
    # DAgger: the first copy, then one round that added the copy's own states, labelled.
    first, second = result["dagger"]
    assert (first["round"], second["round"]) == (0, 1)
    assert first["windows"] == result["windows"] < second["windows"]


def test_a_short_imitate_run_prints_the_documented_json() -> None:
    _check_the_report(_imitate(SLICE), episodes=8, test_episodes=2)


@pytest.mark.slow
def test_imitate_clones_the_planner_and_prints_json() -> None:
    result = _imitate(FULL)
    _check_the_report(result, episodes=48, test_episodes=8)
    # Copying works: most of the planner's decisions, seen or not, are the clone's too.
    assert result["train_agreement"] > 0.8
    assert result["held_out_agreement"] > 0.7
    # Even without obstacles the planner turns where go-to-target would not (it plans the
    # turns' timing), so there are dodges, and the clone's choices on them are counted.
    assert 0.0 < result["dodge_share"] < 0.5
