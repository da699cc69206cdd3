"""The doom judge file: what the lab measured as its tracked shield is what the controller's
judge mode does, episode for episode."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from qnav.controller.lookahead import LookaheadSettings
from qnav.controller.perception import TrackerSettings
from qnav.lab.probe import shielded_go_to_target, tracked_safety
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, evaluate
from qnav.tracking import LookaheadAgent
from tests.conftest import JUDGE_THRESHOLD, judge_network


def test_the_controllers_judge_drives_go_to_target_as_the_labs_tracked_shield(
    make_judge: Callable[[str], Path],
) -> None:
    world = scenario("obstacles-inertia")
    protocol = EvalSettings(episodes=8, num_worlds=8, max_episode_steps=80)
    lab, overruled = shielded_go_to_target(
        world, tracked_safety(world, judge_network()), protocol, JUDGE_THRESHOLD
    )
    judged = LookaheadAgent(
        GoToTargetAgent(),  # type: ignore[arg-type]  # judge mode reads no Q values
        world,
        protocol.num_worlds,
        tracker=TrackerSettings(),
        lookahead=LookaheadSettings(mode="judge", judge_file=str(make_judge(world.name))),
    )
    controller = evaluate(world, judged, protocol)
    assert controller == lab
    # (the two count decisions differently: the lab's drive also asks for finished worlds)
    assert min(judged.overruled_share, overruled) > 0.05, "the judge overruled too little to test"
