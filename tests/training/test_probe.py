"""The perception probe: a supervised fit to doom labels, judged on the held-out gauge."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from contracts.errors import ConfigError
from sim.config import scenario
from sim.decisive import GaugeSettings, collect
from tests.test_cli import _qnav
from training.probe import ProbeSettings, decisive_only, probe

SMALL_GAUGE = GaugeSettings(episodes_per_driver=6, max_episode_steps=40, num_worlds=6)
SMALL = ProbeSettings(episodes_per_driver=6, epochs=2, batch_size=32, threads=1)


def test_an_ordinary_share_keeps_states_where_all_or_no_actions_are_doomed() -> None:
    world = scenario("obstacles-increment")
    only = collect(world, SMALL_GAUGE)
    some = collect(world, replace(SMALL_GAUGE, ordinary_share=0.5))
    assert len(some.doomed) > len(only.doomed)
    assert len(decisive_only(some).doomed) == len(only.doomed)
    np.testing.assert_array_equal(decisive_only(some).windows, only.windows)


def test_each_pass_reports_its_fit_and_the_held_out_gauge() -> None:
    history = probe(scenario("obstacles-increment"), SMALL, SMALL_GAUGE)
    assert [epoch.epoch for epoch in history] == [1, 2]
    for epoch in history:
        assert np.isfinite(epoch.loss) and epoch.loss > 0
        assert 0.0 <= epoch.safe <= 1.0 and 0.0 <= epoch.balanced <= 1.0


def test_a_wrong_probe_setting_names_itself() -> None:
    with pytest.raises(ConfigError, match="epochs"):
        ProbeSettings(epochs=0)
    result = _qnav("probe", "--probe-set", "probe.learning_rate=0", "--json")
    assert result.returncode != 0
    assert "learning_rate" in result.stderr


def test_qnav_probe_prints_its_settings() -> None:
    result = _qnav("probe", "--print-config")
    assert result.returncode == 0, result.stderr
    assert "ordinary_share" in result.stdout
    assert json.dumps(True) not in result.stdout or "scan_difference" in result.stdout
