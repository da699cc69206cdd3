"""The `qnav` command as a user runs it: a real process, real arguments."""

import argparse
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from qnav.cli import build_parser, install_hint
from tests.command import run_qnav

ROOT = Path(__file__).resolve().parents[1]


def _verbs() -> list[str]:
    parser = build_parser()
    verbs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sorted(verbs.choices)


VERBS = _verbs()


@pytest.mark.parametrize("verb", VERBS)
def test_every_verb_has_help(verb: str) -> None:
    result = run_qnav(verb, "--help")
    assert result.returncode == 0
    assert "usage: qnav" in result.stdout


def test_eval_json_prints_one_object_with_the_protocol_fields() -> None:
    result = run_qnav("eval", "--scenario", "walls-increment", "--episodes", "20", "--json")
    assert result.returncode == 0, result.stderr
    values = json.loads(result.stdout)
    assert set(values) == {"success", "collision", "unfinished", "episodes"}
    assert values["episodes"] == 20


def test_bad_setting_exits_with_a_message_naming_it() -> None:
    result = run_qnav("eval", "--scenario", "obstacles-inertia", "--set", "obstacles.count=999")
    assert result.returncode == 2
    assert "obstacles.count = 999 is out of range" in result.stderr
    assert "Traceback" not in result.stderr


def test_unknown_scenario_exits_with_the_list_of_scenarios() -> None:
    result = run_qnav("eval", "--scenario", "moon")
    assert result.returncode == 2
    assert "unknown scenario 'moon'" in result.stderr


def test_bench_sim_json_has_the_documented_shape() -> None:
    result = run_qnav(
        "bench", "sim", "--batches", "1,4", "--seconds", "0.05", "--no-scaling", "--json"
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["scenario"] == "obstacles-inertia"
    assert [(r["batch"], r["driver"]) for r in report["results"]] == [
        (1, "random"), (1, "go-to-target"), (4, "random"), (4, "go-to-target")
    ]  # fmt: skip
    for row in report["results"]:
        assert row["steps_per_second"] > 0 and row["episode_steps"] > 0


def test_bench_lookahead_json_times_each_part_of_the_decision() -> None:
    result = run_qnav("bench", "lookahead", "--decisions", "40", "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["decisions"] >= 40
    for part in ("track", "shield", "plan", "shield_batched"):
        assert 0 < report[f"{part}_ms_p50"] <= report[f"{part}_ms_p99"]


def test_eval_prints_the_world_as_toml_that_eval_accepts(tmp_path) -> None:  # type: ignore[no-untyped-def]
    printed = run_qnav(
        "eval", "--scenario", "obstacles-increment", "--set", "obstacles.count=2", "--print-config"
    )
    assert printed.returncode == 0
    assert "count = 2" in printed.stdout
    path = tmp_path / "world.toml"
    path.write_text(printed.stdout)
    result = run_qnav("eval", "--world-config", str(path), "--episodes", "5", "--json")
    assert result.returncode == 0, result.stderr
    table = run_qnav("eval", "--scenario", "obstacles-increment", "--print-config", "--markdown")
    assert table.stdout.startswith("| setting | value | meaning |")


def test_settings_reference_in_docs_is_current() -> None:
    docs = Path(__file__).resolve().parents[1] / "docs" / "settings.md"
    printed = run_qnav("scenarios", "--reference")
    assert printed.returncode == 0, printed.stderr
    assert docs.read_text() == printed.stdout, "run `make docs` to regenerate"


def _print_config_argv(verb: str, folder: Path) -> list[str]:
    """`verb --print-config`, with what the verb needs besides (serve: a source and a key)."""
    if verb == "serve":
        key = folder / "key.pem"
        key.write_text("unused")
        return [verb, str(folder), "--key", str(key), "--print-config"]
    return [*verb.split(), "--print-config"]


@pytest.mark.parametrize(
    "verb",
    [
        "train",
        "eval",
        "controller",
        "bridge",
        "fake-vehicle",
        "sim-car",
        "serve",
    ],
)
def test_every_verb_with_settings_prints_them_as_toml(verb: str, tmp_path: Path) -> None:
    printed = run_qnav(*_print_config_argv(verb, tmp_path))
    assert printed.returncode == 0, printed.stderr
    assert len(tomllib.loads(printed.stdout)) >= 1


def _without(blocked: str, code: str, folder: Path) -> subprocess.CompletedProcess[str]:
    """Run `code` in a fresh interpreter where `blocked` cannot be imported, as on an install
    that never had it (None in sys.modules: importing it fails, find_spec finds nothing)."""
    return subprocess.run(
        [sys.executable, "-c", f"import sys; sys.modules[{blocked!r}] = None\n{code}"],
        capture_output=True, text=True, timeout=120, check=False, cwd=folder,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("blocked", "argv", "extra"),
    [
        ("torch", ["train", "--scenario", "walls-increment", "--episodes", "2"], "train"),
        ("torch", ["bench", "learner"], "train"),
        ("matplotlib", ["render", "--scenario", "walls-inertia", "--out", "unused"], "viz"),
        # Needed only with this option: named when the import fails.
        ("torch", ["eval", "--policy", "some-run", "--episodes", "2"], "train"),
    ],
)
def test_a_verb_whose_extra_is_not_installed_names_the_extra(
    blocked: str, argv: list[str], extra: str, tmp_path: Path
) -> None:
    # On the car's install (no extras) `qnav train` used to end in a torch traceback.
    done = _without(blocked, f"from qnav.cli import main; sys.exit(main({argv!r}))", tmp_path)
    assert done.returncode == 2, done.stderr[-2000:]
    assert f"pip install -e '.[{extra}]' in the qnav repository" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "Traceback" not in done.stderr


def test_the_install_hint_is_pip_on_this_repository_and_its_extras() -> None:
    # No package index has qnav: `pip install 'qnav[train]'` failed from a clone.
    hint = install_hint(["train", "cluster"])
    assert hint == "pip install -e '.[train,cluster]' in the qnav repository"  # run from a clone
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["name"] == "qnav"
    assert {"train", "cluster"} <= set(project["optional-dependencies"])


def test_help_marks_the_verbs_whose_extra_is_missing(tmp_path: Path) -> None:
    code = "from qnav.cli import main; main(['--help'])"
    shown = _without("torch", code, tmp_path).stdout
    lines = {line.split()[0]: line for line in shown.splitlines() if line.startswith("  ")}
    assert "(needs qnav[train])" in lines["train"]
    assert "(needs" not in lines["eval"]
    full = run_qnav("--help").stdout
    assert "(needs" not in full  # this install has every extra
    assert "other:" not in full  # every verb sits in one of VERB_GROUPS
    assert "research (lab/" in full


def test_train_help_lists_its_generated_options_without_importing_torch(tmp_path: Path) -> None:
    code = (
        "from qnav.cli import main\n"
        "try:\n    main(['train', '--help'])\n"
        "except SystemExit as done:\n    assert done.code == 0\n"
        "print('torch imported' if sys.modules.get('torch') else 'no torch')"
    )
    shown = subprocess.run(
        [sys.executable, "-c", f"import sys\n{code}"],
        capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path,
    )  # fmt: skip
    assert shown.returncode == 0, shown.stderr
    assert "--imitation-rounds" in shown.stdout
    assert shown.stdout.strip().endswith("no torch")
    blocked = _without("torch", code, tmp_path)
    assert blocked.returncode == 0, blocked.stderr
    assert "--imitation-rounds" in blocked.stdout


@pytest.mark.parametrize("verb", ["controller", "bridge", "fake-vehicle"])
def test_every_daemon_prints_its_settings_with_one_spelling_and_reads_them_back(
    verb: str, tmp_path: Path
) -> None:
    printed = run_qnav(verb, "--print-config")
    assert printed.returncode == 0, printed.stderr
    path = tmp_path / "settings.toml"
    path.write_text(printed.stdout)
    again = run_qnav(verb, "--config", str(path), "--print-config")
    assert again.returncode == 0, again.stderr
    assert again.stdout == printed.stdout


@pytest.mark.parametrize(
    ("verb", "target"),
    [
        ("controller", "qnav.controller.config:DaemonConfig"),
        ("bridge", "qnav.firmware_bridge.settings:BridgeSettings"),
        ("fake-vehicle", "qnav.simcar.mavlink_vehicle:MavlinkVehicleSettings"),
    ],
)
def test_help_lists_every_setting_with_its_value_and_documentation(verb: str, target: str) -> None:
    import importlib

    from qnav.contracts.settings import to_listing

    module, name = target.split(":")
    settings = getattr(importlib.import_module(module), name)()
    shown = run_qnav(verb, "--help")
    assert shown.returncode == 0, shown.stderr
    listing = to_listing(settings)
    assert listing.count(" = ") >= 10
    for line in listing.splitlines():
        if " = " in line:
            assert line.split(" = ")[0] + " = " in shown.stdout, line


def test_controller_print_config_is_the_settings_it_would_run_with(tmp_path: Path) -> None:
    # It printed the defaults whatever --config, --set and --policy said (issue 53).
    config = tmp_path / "car.toml"
    config.write_text("[safety]\nscan_timeout_s = 0.7\n")
    policy = tmp_path / "policy.onnx"
    printed = run_qnav(
        "controller", "--config", str(config), "--set", "controller.trigger=\"scan\"",
        "--policy", str(policy), "--print-config",
    )  # fmt: skip
    assert printed.returncode == 0, printed.stderr
    settings = tomllib.loads(printed.stdout)
    assert settings["safety"]["scan_timeout_s"] == 0.7
    assert settings["controller"]["trigger"] == "scan"
    assert settings["controller"]["policy"] == str(policy)
    assert "the values shown are the defaults" not in printed.stdout
    again = tmp_path / "again.toml"
    again.write_text(printed.stdout)
    assert run_qnav("controller", "--config", str(again), "--print-config").stdout == printed.stdout


@pytest.mark.parametrize(
    ("verb", "key"),
    [
        ("controller", "safety.scan_timout_s"),
        ("bridge", "failsafe.comand_timeout_s"),
        ("fake-vehicle", "dynamics.max_sped_mps"),
    ],
)
def test_print_config_refuses_a_mistyped_setting_naming_it(verb: str, key: str) -> None:
    printed = run_qnav(verb, "--set", f"{key}=1.0", "--print-config")
    assert printed.returncode == 2, printed.stdout
    assert printed.stdout == ""
    assert f"unknown setting {key!r}" in printed.stderr
    assert "Traceback" not in printed.stderr
