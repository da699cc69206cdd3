"""Doubt-led labelling: rounds of drive, label the doubtful, refit, kept in a folder that
resumes."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import get_type_hints

import numpy as np
import pytest
import torch
from numpy.typing import NDArray

from qnav.contracts.actions import NUM_ACTIONS
from qnav.contracts.errors import ConfigError
from qnav.controller.judge import DoomJudge
from qnav.lab.decisive import GaugeSettings
from qnav.lab.doubt import (
    THRESHOLDS,
    DoubtSettings,
    LabelFolder,
    LabelledRound,
    RoundReport,
    doubt,
    drive_and_label,
    most_doubtful,
    redraw_and_label,
    run_rounds,
)
from qnav.lab.probe import ProbeSettings, judged_safe, network_safety, tracked_safety
from qnav.lab.redrawn import stored_steps
from qnav.sim.config import scenario
from qnav.sim.evaluate import drive, go_to_target
from qnav.sim.world import Observation, WorldState
from tests.command import run_qnav
from tests.lab.conftest import TINY_RUN_WORLD

SMALL_GAUGE = GaugeSettings(episodes_per_driver=6, max_episode_steps=40, num_worlds=6)
SMALL_PROBE = ProbeSettings(
    inputs="slots", episodes_per_driver=6, epochs=2, batch_size=32, threads=1
)
SMALL = DoubtSettings(episodes_per_round=8, num_worlds=4, max_episode_steps=40, shield_episodes=4)
SMALL_ARGS = (
    "--scenario",
    "obstacles-increment",
    *("--probe-set", "probe.episodes_per_driver=6", "--probe-set", "probe.epochs=2"),
    *("--probe-set", "probe.batch_size=32", "--probe-set", "probe.threads=1"),
    *("--probe-set", "doubt.episodes_per_round=8", "--probe-set", "doubt.num_worlds=4"),
    *("--probe-set", "doubt.max_episode_steps=40", "--probe-set", "doubt.shield_episodes=4"),
    *("--probe-set", "gauge.episodes_per_driver=6", "--probe-set", "gauge.max_episode_steps=40"),
    *("--probe-set", "gauge.num_worlds=6"),
)


def test_the_most_doubtful_states_have_an_action_nearest_even_odds() -> None:
    safe_probability = np.array(
        [
            [0.99, 0.01, 0.98],  # sure of every action
            [0.99, 0.55, 0.02],  # unsure of one
            [0.70, 0.30, 0.90],
            [0.50, 0.99, 0.99],  # even odds on one
        ]
    )
    assert most_doubtful(safe_probability, 0.5).tolist() == [3, 1]
    assert most_doubtful(safe_probability, 0.01).tolist() == [3]
    assert most_doubtful(safe_probability[:0], 0.5).tolist() == []


def test_a_round_labels_its_share_of_the_visited_states_and_reads_back_unchanged(
    tmp_path: Path,
) -> None:
    world = scenario("obstacles-increment")

    def unsure(state: WorldState, observation: Observation) -> NDArray[np.float64]:
        return np.full((len(state.steps), NUM_ACTIONS), 0.5)

    labelled = drive_and_label(world, unsure, SMALL, round_index=1)
    batches = SMALL.episodes_per_round // SMALL.num_worlds
    assert labelled.visited > 0
    # each batch of worlds keeps its own share, rounded
    assert abs(len(labelled.collide_share) - SMALL.labelled_share * labelled.visited) <= batches
    assert labelled.context.shape[0] == labelled.slots.shape[0] == len(labelled.world.steps)
    assert ((labelled.collide_share >= 0) & (labelled.collide_share <= 1)).all()
    labelled.save(tmp_path / "round.npz")
    back = LabelledRound.load(tmp_path / "round.npz")
    assert back.visited == labelled.visited
    for name in ("context", "slots", "collide_share"):
        np.testing.assert_array_equal(getattr(back, name), getattr(labelled, name))
    for name in labelled.world._fields:
        np.testing.assert_array_equal(getattr(back.world, name), getattr(labelled.world, name))


def _without_minutes(reports: list[RoundReport]) -> list[RoundReport]:
    return [report._replace(minutes=0.0) for report in reports]


def test_a_resumed_folder_holds_the_rounds_of_a_run_straight_through(tmp_path: Path) -> None:
    world = scenario("obstacles-increment")
    settings = {"probe": SMALL_PROBE, "settings": SMALL, "gauge": SMALL_GAUGE}
    straight = list(run_rounds(world, tmp_path / "straight", 2, **settings))  # type: ignore[arg-type]
    assert [report.round for report in straight] == [0, 1, 2]
    list(run_rounds(world, tmp_path / "resumed", 1, **settings))  # type: ignore[arg-type]
    # a run killed while writing round 2 leaves only a partial file behind
    (tmp_path / "resumed" / "round-002.partial.npz").write_bytes(b"cut short")
    first_round = (tmp_path / "resumed" / "round-001.npz").stat().st_mtime_ns
    resumed = list(run_rounds(world, tmp_path / "resumed", 2, **settings))  # type: ignore[arg-type]
    assert (tmp_path / "resumed" / "round-001.npz").stat().st_mtime_ns == first_round
    assert _without_minutes(resumed) == _without_minutes(straight)
    read_back = LabelFolder(tmp_path / "resumed").reports()
    assert _without_minutes(read_back) == _without_minutes(straight)
    kinds = get_type_hints(RoundReport)  # counts come back as counts, not as 13.0
    assert all(isinstance(getattr(r, f), kinds[f]) for r in read_back for f in RoundReport._fields)
    for first, second in zip(
        LabelFolder(tmp_path / "straight").rounds(),
        LabelFolder(tmp_path / "resumed").rounds(),
        strict=True,
    ):
        np.testing.assert_array_equal(first.collide_share, second.collide_share)
    # every decisive state labelled is fitted to; the rounds add up
    base = straight[0].fitted_decisive
    for report in straight[1:]:
        base += report.labelled_decisive
        assert report.fitted_decisive == base
    assert straight[2].fitted_states > straight[1].fitted_states > straight[0].fitted_states
    assert (tmp_path / "straight" / "progress.png").stat().st_size > 0


def test_a_folder_refuses_rounds_made_otherwise_and_names_the_setting(tmp_path: Path) -> None:
    world = scenario("obstacles-increment")
    list(run_rounds(world, tmp_path, 0, probe=SMALL_PROBE, settings=SMALL, gauge=SMALL_GAUGE))
    with pytest.raises(ConfigError, match=r"labelled_share = 0\.5"):
        run_rounds(
            world,
            tmp_path,
            1,
            probe=SMALL_PROBE,
            settings=replace(SMALL, labelled_share=0.5),
            gauge=SMALL_GAUGE,
        )


@pytest.mark.parametrize(
    ("setting", "value"),
    [
        ("inputs", "lidar"),  # judged from a window of scans, which the rounds do not render
        ("labelled_actions", "taken"),  # the rounds record no driver's action
    ],
)
def test_rounds_the_doubt_led_labelling_cannot_make_are_refused_by_name(
    tmp_path: Path, setting: str, value: str
) -> None:
    with pytest.raises(ConfigError, match=rf"probe\.{setting}"):
        run_rounds(
            scenario("obstacles-increment"),
            tmp_path,
            1,
            probe=replace(SMALL_PROBE, **{setting: value}),  # type: ignore[arg-type]
            settings=SMALL,
            gauge=SMALL_GAUGE,
        )
    assert not (tmp_path / "settings.toml").exists()


def test_the_command_prints_a_round_per_line_and_resumes(tmp_path: Path) -> None:
    folder = str(tmp_path / "rounds")
    first = run_qnav("lab", "label", folder, "--rounds", "1", *SMALL_ARGS, "--json")
    assert first.returncode == 0, first.stderr
    rounds = [json.loads(line) for line in first.stdout.splitlines()]
    assert [row["round"] for row in rounds] == [0, 1]
    judge = tmp_path / "judge.onnx"
    tested = run_qnav(
        "lab", "label", folder, "--rounds", "1", *SMALL_ARGS, "--test-episodes", "3", "--json",
        "--export", str(judge),
    )  # fmt: skip
    assert tested.returncode == 0, tested.stderr
    test = json.loads(tested.stdout.splitlines()[-1])["final_test"]
    assert test["threshold"] in THRESHOLDS
    assert test["validation"][str(test["threshold"])] == max(test["validation"].values())
    for result in ("half", "truth", "tracked", "tracked_noisy"):
        assert test[result]["episodes"] == 3
    # The exported judge carries the chosen threshold and the test's figures, and the
    # controller's judge mode, in process, drives go-to-target as the test's tracked shield did.
    contract = DoomJudge(judge).contract
    assert (contract.threshold, contract.evaluation["success"]) == (
        test["threshold"],
        test["truth"]["success"],
    )
    assert contract.training["rounds"] == 1
    driven = run_qnav(
        "eval", "--scenario", "obstacles-increment", "--agent", "goto", "--lookahead", "judge",
        "--judge", str(judge), "--episodes", "3", "--json",
    )  # fmt: skip
    assert driven.returncode == 0, driven.stderr
    assert json.loads(driven.stdout)["success"] == test["tracked"]["success"]
    again = run_qnav("lab", "label", folder, "--rounds", "1", *SMALL_ARGS, "--json")
    assert again.returncode == 0, again.stderr
    assert [json.loads(line) for line in again.stdout.splitlines()] == rounds
    other = run_qnav("lab", "label", folder, *SMALL_ARGS, "--probe-set", "doubt.seed=1")
    assert other.returncode != 0
    assert "seed = 1" in other.stderr


def test_the_command_lists_its_settings_and_names_a_wrong_one() -> None:
    listed = run_qnav("lab", "label", "--print-config")
    assert listed.returncode == 0, listed.stderr
    for section in ("[probe]", "[doubt]", "[gauge]", "labelled_share = 0.2", 'inputs = "slots"'):
        assert section in listed.stdout
    wrong = run_qnav("lab", "label", "somewhere", "--probe-set", "doubt.labelled_share=0")
    assert wrong.returncode != 0
    assert "labelled_share" in wrong.stderr


def test_a_shielded_round_drives_where_the_judgement_takes_the_robot() -> None:
    world = scenario("obstacles-increment")

    def only_the_first_action_is_safe(
        state: WorldState, observation: Observation
    ) -> NDArray[np.float64]:
        judged = np.full((len(state.steps), NUM_ACTIONS), 0.2)
        judged[:, 0] = 0.9
        return judged

    blind = replace(SMALL, driver="go-to-target")
    alone = drive_and_label(world, only_the_first_action_is_safe, blind, round_index=1)
    shielded = drive_and_label(world, only_the_first_action_is_safe, SMALL, round_index=1)
    # the shield takes the first action wherever go-to-target wanted another: other states
    assert not np.array_equal(alone.world.pose, shielded.world.pose)


def test_reworded_comments_do_not_stop_a_folder_from_resuming(tmp_path: Path) -> None:
    folder = LabelFolder(tmp_path)
    folder.claim("# old words\n[doubt]\nseed = 1\n")
    folder.claim("# new words\n[doubt]\n# more\nseed = 1\n")
    with pytest.raises(ConfigError, match="seed = 2"):
        folder.claim("[doubt]\nseed = 2\n")


class _NearestAhead(torch.nn.Module):
    """Logits that are the nearest obstacle slot's distance ahead: what the network was shown."""

    def forward(self, context: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        return slots[:, 0, 1:2].expand(-1, NUM_ACTIONS) * 1.0


def test_the_tracker_shows_the_fit_the_obstacles_the_truth_shows_it() -> None:
    world = scenario("obstacles-inertia")
    network = _NearestAhead()
    truth = network_safety(world, network, "slots")
    exact_scans = tracked_safety(world, network)
    noisy_scans = tracked_safety(world, network, range_noise_m=0.02)
    seen: list[tuple[NDArray[np.floating], ...]] = []

    def act(state: WorldState, observation: Observation) -> NDArray[np.int64]:
        judged = tuple(
            safety(state, observation)[:, 0] for safety in (truth, exact_scans, noisy_scans)
        )
        if state.steps.min() >= 5:  # the tracker has seen the obstacles move
            seen.append(judged)
        return go_to_target(observation.target_features())

    drive(replace(world, max_episode_steps=30), 7, np.arange(4), act)
    exact, from_exact_scans, from_noisy_scans = (
        np.concatenate(column) for column in zip(*seen, strict=True)
    )
    assert len(exact) > 20
    # the nearest obstacle, ahead: the tracker finds it where it is, within noise
    np.testing.assert_allclose(from_exact_scans, exact, atol=1e-3)
    assert 0 < np.median(np.abs(from_noisy_scans - exact)) < 0.01


def test_rounds_among_redrawn_obstacles_label_the_runs_own_steps_and_resume(
    tiny_run: Path, tmp_path: Path
) -> None:
    probe = replace(SMALL_PROBE, redrawn_from=str(tiny_run), redrawn_states=400)
    settings = {"probe": probe, "settings": SMALL, "gauge": SMALL_GAUGE}
    straight = list(run_rounds(TINY_RUN_WORLD, tmp_path / "straight", 2, **settings))  # type: ignore[arg-type]
    assert [report.round for report in straight] == [0, 1, 2]
    assert all(report.visited == 400 for report in straight)
    assert all(report.labelled == 80 for report in straight[1:])  # the doubtful fifth
    resumed = tmp_path / "resumed"
    list(run_rounds(TINY_RUN_WORLD, resumed, 1, **settings))  # type: ignore[arg-type]
    labelled_once = (resumed / "round-000.npz").stat().st_mtime_ns
    again = list(run_rounds(TINY_RUN_WORLD, resumed, 2, **settings))  # type: ignore[arg-type]
    assert (resumed / "round-000.npz").stat().st_mtime_ns == labelled_once  # not relabelled
    assert _without_minutes(again) == _without_minutes(straight)
    steps = stored_steps(TINY_RUN_WORLD, tiny_run, window=SMALL_GAUGE.window)
    visited = {tuple(row) for row in np.round(steps.pose, 9)}
    for labelled in LabelFolder(resumed).rounds():
        assert all(tuple(row) in visited for row in np.round(labelled.world.pose, 9))


def test_a_redrawn_round_labels_the_most_doubtful_of_its_drawn_states(tiny_run: Path) -> None:
    steps = stored_steps(TINY_RUN_WORLD, tiny_run, window=5)
    probe = replace(SMALL_PROBE, redrawn_from=str(tiny_run), redrawn_states=300)
    network = _NearestAhead()

    def round_with(share: float) -> LabelledRound:
        settings = replace(SMALL, labelled_share=share)
        return redraw_and_label(
            TINY_RUN_WORLD, steps, network, probe, settings, round_index=1, window=5
        )

    every, doubtful = round_with(1.0), round_with(0.2)
    assert every.visited == doubtful.visited == 300 and len(doubtful.collide_share) == 60
    judged = judged_safe(network, (every.context, every.slots))
    chosen = judged_safe(network, (doubtful.context, doubtful.slots))
    # the same draws, of which the fifth whose judgement is nearest even odds was labelled
    assert doubt(chosen).max() <= np.sort(doubt(judged))[59]
