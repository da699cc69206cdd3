"""`make demo` stays light and shows the shipped controller: it installs the [train] extra, not
[dev] (no linters, mypy or SB3), with its own stamp, while `make test` installs [dev]; the
obstacles policy it drives is committed."""

import re
from pathlib import Path

import pytest

from qnav import demo

ROOT = Path(__file__).resolve().parents[1]


def _recipe(target: str) -> str:
    """The Makefile's rule for `target`: its line and the recipe's tab-indented lines."""
    text = (ROOT / "Makefile").read_text()
    match = re.search(rf"^{re.escape(target)}:.*\n((?:\t.*\n)*)", text, re.M)
    assert match, f"no rule for {target}"
    return match.group(0)


def test_the_demo_installs_the_train_extra_and_the_tests_the_dev_one() -> None:
    demo_rule = _recipe("demo")
    assert "$(DEMO_STAMP)" in demo_rule and "qnav.demo" in demo_rule
    install = _recipe("$(DEMO_STAMP)")
    assert "'.[train]'" in install and "dev" not in install and "--quiet" not in install
    assert "'.[dev]'" in _recipe("$(STAMP)")
    for target in ("lint", "typecheck", "pytest"):
        assert "$(STAMP)" in _recipe(target)


def test_the_demo_drives_the_committed_obstacles_policy() -> None:
    assert (ROOT / demo.OBSTACLES_POLICY).is_file()


def test_the_demo_says_how_long_each_step_took(capsys: pytest.CaptureFixture[str]) -> None:
    steps = demo._Steps()
    steps.next(1, "training", "Training")
    steps.next(2, "stack", "Stack")
    summary = steps.summary()
    assert "1/4  Training" in capsys.readouterr().out
    assert summary.startswith("done in ") and "(training 0 s, stack 0 s)" in summary


def test_a_failed_background_command_raises_with_its_errors() -> None:
    failing = demo._background([["eval", "--no-such-option"]])
    with failing as runs, pytest.raises(RuntimeError, match="no-such-option"):
        demo._report(runs)


def test_background_commands_still_running_are_killed_on_the_way_out() -> None:
    endless = ["eval", "--scenario", "obstacles-inertia", "--agent", "goto", "--episodes=100000"]
    with pytest.raises(KeyboardInterrupt), demo._background([endless]) as runs:
        raise KeyboardInterrupt
    assert runs[0][1].returncode is not None
