"""The daemon's settings file, its command line, and the loop's pacing and logging parts."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import pytest

from qnav.cli import main
from qnav.contracts import wire
from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import field_docs, from_dict, load_toml, to_markdown
from qnav.controller.config import DaemonConfig, load_config
from qnav.controller.daemon import Daemon, Ratekeeper, build, commented_config
from qnav.controller.decision import Controller, Input
from qnav.controller.policy import PolicyRuntime
from tests.conftest import PolicyFactory

ROOT = Path(__file__).resolve().parents[2]


def test_the_config_file_in_the_repo_is_what_the_daemon_prints_and_holds_the_defaults() -> None:
    text = (ROOT / "config" / "controller.toml").read_text()
    assert text == commented_config()
    assert from_dict(DaemonConfig, load_toml(ROOT / "config" / "controller.toml")) == DaemonConfig()


def test_the_shipped_settings_run_the_shield_and_the_proximity_stop(
    make_policy: PolicyFactory,
) -> None:
    shipped = ROOT / "config" / "controller.toml"
    policy = f'controller.policy="{make_policy("obstacles-inertia")}"'
    daemon = build(load_config(shipped, [policy, "lookahead.room_size_m=10.0"]))
    assert daemon.controller.lookahead is not None
    assert daemon.controller.lookahead_settings.mode == "shield"
    assert daemon.controller.proximity.enabled


@pytest.mark.parametrize(
    ("scenario", "named"),
    [
        ("obstacles-inertia", "lookahead.room_size_m is not set"),  # the room's walls
        ("toycar-inertia", 'set lookahead.mode = "off"'),  # a policy that reads no lidar
    ],
)
def test_the_shipped_settings_refuse_to_start_naming_what_the_shield_needs(
    capsys: pytest.CaptureFixture[str], make_policy: PolicyFactory, scenario: str, named: str
) -> None:
    shipped = str(ROOT / "config" / "controller.toml")
    policy = str(make_policy(scenario))
    assert main(["controller", "--config", shipped, "--policy", policy]) == 2
    assert named in capsys.readouterr().err


def test_every_setting_is_documented() -> None:
    for section in dataclasses.fields(DaemonConfig):
        cls = (
            section.type
            if isinstance(section.type, type)
            else type(getattr(DaemonConfig(), section.name))
        )
        docs = field_docs(cls)
        for f in dataclasses.fields(cls):
            assert docs.get(f.name), f"{section.name}.{f.name} has no documentation"


def test_a_relative_policy_path_is_taken_from_the_settings_files_folder(tmp_path: Path) -> None:
    (tmp_path / "cfg").mkdir()
    path = tmp_path / "cfg" / "controller.toml"
    path.write_text('[controller]\npolicy = "policy.onnx"\n[lidar]\nuncovered_range_m = 0.0\n')
    config = load_config(path, ["safety.target_tolerance_m=0.2"])
    assert Path(config.controller.policy) == tmp_path / "cfg" / "policy.onnx"
    assert config.lidar.uncovered_range_m == 0.0
    assert config.safety.target_tolerance_m == 0.2


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("[safety]\ntarget_tolerance_m = -1.0\n", "safety.target_tolerance_m"),
        ("[lidar]\nmax_invalid_fraction = 2.0\n", "lidar.max_invalid_fraction"),
        ('[controller]\ntrigger = "sometimes"\n', "controller.trigger"),
        ("[safety]\nscan_timeout = 1.0\n", "scan_timeout"),
        ('[zenoh]\nlisten = ["localhost"]\n', "zenoh.listen"),
        ('[topics]\nscan = "scan/*"\n', "topics.scan"),
        ("[lookahead]\noverrule_share = 1.5\n", "lookahead.overrule_share"),
        ("[lookahead]\ntolerance = 0.1\n", "lookahead.tolerance"),  # removed on 2026-12-06
        ("[controller]\n", "controller.policy"),
        ('[controller]\npolicy = "missing.onnx"\n', "controller.policy"),
    ],
)
def test_a_wrong_setting_exits_2_naming_the_setting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, named: str
) -> None:
    path = tmp_path / "controller.toml"
    path.write_text(text)
    assert main(["controller", "--config", str(path)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("qnav controller: ")
    assert named in error


def test_a_policy_that_is_not_a_policy_file_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bogus = tmp_path / "policy.onnx"
    bogus.write_bytes(b"not onnx")
    assert main(["controller", "--policy", str(bogus)]) == 2
    assert str(bogus) in capsys.readouterr().err


def test_ratekeeper_deadlines_stay_on_the_grid_whatever_each_tick_costs() -> None:
    rate = Ratekeeper(0.2, 100.0)
    for n in range(1, 50):
        missed = rate.advance(rate.deadline + 0.15 * ((n * 7) % 10) / 10)  # work < a period
        assert missed == 0
        assert rate.deadline == pytest.approx(100.0 + 0.2 * n, abs=1e-9)


def test_ratekeeper_counts_and_skips_the_deadlines_an_overrun_missed() -> None:
    rate = Ratekeeper(0.2, 0.0)
    assert rate.advance(0.45) == 2  # deadlines 0.2 and 0.4 have passed
    assert rate.deadline == pytest.approx(0.6)
    assert rate.advance(0.85) == 1  # the work of deadline 0.6 ran past 0.8
    assert rate.deadline == pytest.approx(1.0)
    assert rate.advance(1.1) == 0


def test_keys_follow_zenoh_bridge_ros2dds_with_the_namespace(make_policy: PolicyFactory) -> None:
    config = from_dict(
        DaemonConfig,
        {"zenoh": {"namespace": "/car1/"}, "safety": {"target_kind": "point"}},
    )
    daemon = Daemon(config, Controller(PolicyRuntime(make_policy("walls-inertia"))))
    assert daemon.keys == {
        Input.SCAN: "car1/scan",
        Input.POSE: "car1/pose",
        Input.TARGET: "car1/goal_point",
        Input.ESTOP: "car1/estop",
        Input.ESTOP_RELEASE: "car1/qnav/estop_release",
    }
    assert (daemon.command_key, daemon.status_key) == (
        "car1/cmd_vel",
        "car1/qnav/controller_status",
    )
    lidarless = Daemon(config, Controller(PolicyRuntime(make_policy("toycar-inertia"))))
    assert Input.SCAN not in lidarless.keys
    assert wire.key(wire.SCAN) == "scan"


def test_uncovered_range_must_be_a_range() -> None:
    with pytest.raises(ConfigError, match=r"lidar\.uncovered_range_m"):
        from_dict(DaemonConfig, {"lidar": {"uncovered_range_m": math.nan}})


def test_the_docs_describe_every_setting() -> None:
    text = (ROOT / "docs" / "controller-settings.md").read_text()
    names = re.findall(r"^\| `([a-z_.]+)` \| (?!\(section\))", to_markdown(DaemonConfig()), re.M)
    assert len(names) > 25
    missing = [name for name in names if f"| `{name}` |" not in text]
    assert not missing
