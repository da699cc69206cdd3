"""The audit of a policy's judgements: exact judgements never take a doomed action where a safe
one exists, auditing a drive does not change it, and a judge that cannot judge is refused first."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from qnav.contracts.errors import PolicyFileError
from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.lab.audit import audit
from qnav.sim.evaluate import EvalSettings, evaluate
from qnav.tracking import LookaheadAgent
from qnav.training.agent import TorchAgent, policy_agent
from qnav.training.run_folder import load_network
from tests.lab.conftest import TINY_RUN_WORLD

PROTOCOL = EvalSettings(episodes=8, num_worlds=8, max_episode_steps=60, seed=5)


def test_exact_judgements_take_a_safe_action_in_every_decisive_state(tiny_run: Path) -> None:
    rows = {row.judgement: row for row in audit(tiny_run, PROTOCOL)}
    assert set(rows) == {"alone", "doom labels", "collision shares", "forecast"}
    exact = [rows["doom labels"], rows["collision shares"]]
    assert sum(row.decisive for row in exact) > 0, "no decisive state met: nothing tested"
    for row in exact:
        assert row.decisive == 0 or row.taken_safe == 1.0, row
    alone = rows["alone"]
    assert alone.overruled == 0.0 and alone.taken_safe == alone.policy_safe


def test_auditing_a_drive_leaves_its_outcomes_as_the_test_protocols(
    tiny_run: Path, make_judge: Callable[[str], Path]
) -> None:
    judge = make_judge(TINY_RUN_WORLD.name)
    rows = {row.judgement: row for row in audit(tiny_run, PROTOCOL, judge)}
    network, run = load_network(tiny_run)

    def policy() -> TorchAgent:
        return policy_agent(network, TINY_RUN_WORLD, PROTOCOL.num_worlds, run.train.window)

    judged = LookaheadAgent(
        policy(),
        TINY_RUN_WORLD,
        PROTOCOL.num_worlds,
        tracker=TrackerSettings(),
        lookahead=LookaheadSettings(mode="judge", judge_file=str(judge)),
        seed=PROTOCOL.seed,
    )
    assert rows["alone"].result == evaluate(TINY_RUN_WORLD, policy(), PROTOCOL)
    assert rows["judge file"].result == evaluate(TINY_RUN_WORLD, judged, PROTOCOL)
    alone = rows["alone"]
    assert alone.decisions == round(alone.result.mean_steps * alone.result.episodes)


def test_a_judge_of_another_world_is_refused_before_any_drive(
    tiny_run: Path, make_judge: Callable[[str], Path]
) -> None:
    other = make_judge("obstacles-increment")
    with pytest.raises(PolicyFileError, match="increment dynamics"):
        audit(tiny_run, PROTOCOL, other)
    with pytest.raises(PolicyFileError, match="does not exist"):
        audit(tiny_run, PROTOCOL, other.with_name("missing.onnx"))


def test_auditing_the_policy_alone_gives_the_full_audits_alone_row(tiny_run: Path) -> None:
    (alone,) = audit(tiny_run, PROTOCOL, judgements=("alone",))
    full = {row.judgement: row for row in audit(tiny_run, PROTOCOL)}
    assert alone == full["alone"]
    assert alone.decisive_per_episode == alone.decisive / PROTOCOL.episodes
