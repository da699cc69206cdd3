"""A health file is fresh only while its daemon's loop beats; every failure says why."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from qnav.contracts.health import HEALTH_FILE_ENV, Heartbeat, check_health, health_path


def test_a_fresh_beat_is_healthy_and_shows_its_daemon_and_detail(tmp_path: Path) -> None:
    path = tmp_path / "health.json"
    Heartbeat("controller", path).beat(reason="policy")
    healthy, explanation = check_health(path, max_age_s=5.0)
    assert healthy, explanation
    assert "controller" in explanation and "reason=policy" in explanation


def test_a_beat_older_than_the_limit_is_unhealthy_with_its_age(tmp_path: Path) -> None:
    path = tmp_path / "health.json"
    Heartbeat("bridge", path).beat()
    healthy, explanation = check_health(path, max_age_s=5.0, now_s=time.monotonic() + 12.0)
    assert not healthy
    assert "last beat 12.0 s ago (limit 5 s)" in explanation


def test_beats_closer_than_the_period_do_not_rewrite_the_file(tmp_path: Path) -> None:
    path = tmp_path / "health.json"
    heartbeat = Heartbeat("recorder", path, every_s=60.0)
    heartbeat.beat(messages=1)
    heartbeat.beat(messages=2)
    assert json.loads(path.read_text())["detail"] == {"messages": 1}


def test_a_clean_exit_removes_the_file_and_a_missing_file_names_the_variable(
    tmp_path: Path,
) -> None:
    path = tmp_path / "health.json"
    heartbeat = Heartbeat("controller", path)
    heartbeat.beat()
    heartbeat.close()
    healthy, explanation = check_health(path)
    assert not healthy and HEALTH_FILE_ENV in explanation and str(path) in explanation


@pytest.mark.parametrize("text", ["", "{not json", '{"daemon": "x"}', "[1, 2]"])
def test_a_corrupt_file_is_unhealthy_not_an_exception(tmp_path: Path, text: str) -> None:
    path = tmp_path / "health.json"
    path.write_text(text)
    healthy, explanation = check_health(path)
    assert not healthy and explanation.startswith("unreadable health file")


def test_without_the_variable_a_heartbeat_writes_nothing(tmp_path: Path) -> None:
    assert health_path({}) is None
    assert health_path({HEALTH_FILE_ENV: str(tmp_path / "h.json")}) == tmp_path / "h.json"
    Heartbeat("controller", None).beat()  # no file, no error
    assert list(tmp_path.iterdir()) == []


def test_an_unwritable_file_is_logged_once_and_never_raises(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    heartbeat = Heartbeat("bridge", tmp_path / "missing-dir" / "health.json", every_s=0.0)
    heartbeat.beat()
    heartbeat.beat()
    assert len([r for r in caplog.records if "cannot write the health file" in r.message]) == 1
