# Ad hoc measurement of issue 19 (2026-12-06); runs against commit 0475843 and later.
"""Does a safety margin in the doom labels make a judge's misses less costly?

The judged DQN keeps its action until the judge calls it doomed (every continuation collides
within 4 s), so the DQN rides the edge: where the judge misses, the next state is lost. A judge
fitted to labels of an inflated obstacle radius (doomed = every continuation comes within
radius + margin) would overrule a little earlier, leaving slack for the next decision.

Gauge (no fitting): drive a run's greedy DQN over the test protocol's first N layouts, judged by
the EXACT labels of obstacles inflated by `margin` (judge rule, threshold 1/2), and with
probability `miss` per decision the judgement is skipped (the DQN's action kept): a judge whose
misses are independent from step to step, at the learned judge's miss rate (it took a safe action
in 0.866 of the decisive states it met; audit). Every state is also labelled with the true
radius: decisive states met, taken safe.

Usage: margin_gauge.py RUN EPISODES MARGIN[,MARGIN...] MISS[,MISS...] [judge|shield]
(shield: the shield rule on the exact collision shares instead, the policy's best-valued action
among the least colliding, with the same independent misses.)
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from qnav.contracts.judge_file import judged_actions
from qnav.contracts.lookahead import shielded_actions
from qnav.lab.decisive import is_decisive
from qnav.lab.oracle import collision_shares, doom_label_safety
from qnav.sim.evaluate import EvalResult, EvalSettings, episode_outcomes
from qnav.sim.world import take_rows
from qnav.training.agent import policy_agent
from qnav.training.run_folder import load_network


class MarginJudged:
    def __init__(self, policy, world, margin_m, miss, seed, rule="judge"):  # type: ignore[no-untyped-def]
        self.policy, self.world, self.miss, self.rule = policy, world, miss, rule
        obstacles = replace(world.obstacles, radius_m=world.obstacles.radius_m + margin_m)
        self.judge_world = replace(world, obstacles=obstacles) if margin_m else world
        self.random = np.random.default_rng(seed)
        self.state = None
        self.counting = np.zeros(0, dtype=bool)
        self.decisions = self.decisive = self.taken_safe = self.overruled = 0

    def watch(self, state, counting):  # type: ignore[no-untyped-def]
        self.state, self.counting = state, counting.copy()

    def start(self, worlds, episodes):  # type: ignore[no-untyped-def]
        self.policy.start(worlds, episodes)

    def act(self, observation):  # type: ignore[no-untyped-def]
        counted = np.flatnonzero(self.counting)
        rows = take_rows(self.state, counted)
        truth = np.zeros((len(self.counting), 3))
        truth[counted] = collision_shares(self.world, rows)
        judged_share = truth
        if self.judge_world is not self.world:
            judged_share = np.zeros_like(truth)
            judged_share[counted] = collision_shares(self.judge_world, rows)
        preferred = self.policy.act(observation)
        judged = judged_actions(preferred, doom_label_safety(judged_share), 0.5)
        if self.rule.startswith("share"):  # "share0.9": doomed where at least 0.9 of them collide
            doom_share = float(self.rule[5:])
            safety = np.where(judged_share >= doom_share, 0.5 - judged_share / 4,
                              1 - judged_share / 2)
            judged = judged_actions(preferred, safety, 0.5)
        if self.rule == "shield":
            judged = shielded_actions(self.policy.last_q, judged_share, 0.0)
        missed = self.random.random(len(preferred)) < self.miss
        taken = np.where(missed, preferred, judged)
        doomed = truth == 1.0
        decisive = np.flatnonzero(self.counting & is_decisive(doomed))
        self.decisions += int(self.counting.sum())
        self.decisive += decisive.size
        self.taken_safe += int((~doomed[decisive, taken[decisive]]).sum())
        self.overruled += int((taken != preferred)[self.counting].sum())
        return taken


def main() -> None:
    torch.set_num_threads(1)
    run, episodes = Path(sys.argv[1]), int(sys.argv[2])
    margins = [float(m) for m in sys.argv[3].split(",")]
    misses = [float(m) for m in sys.argv[4].split(",")]
    rule = sys.argv[5] if len(sys.argv) > 5 else "judge"
    network, folder = load_network(run)
    world = folder.world
    protocol = EvalSettings(episodes=episodes)
    worlds = min(protocol.num_worlds, episodes)
    for margin in margins:
        for miss in misses:
            started = time.time()
            policy = policy_agent(network, world, worlds, folder.train.window, seed=protocol.seed)
            agent = MarginJudged(policy, world, margin, miss, seed=7, rule=rule)
            outcomes = episode_outcomes(world, agent, protocol, watch=agent.watch)
            result = EvalResult.of_outcomes(*outcomes)
            print(json.dumps({
                "rule": rule, "margin_m": margin, "miss": miss, "success": result.success,
                "collision": result.collision, "decisive_per_episode": agent.decisive / episodes,
                "taken_safe": agent.taken_safe / max(agent.decisive, 1),
                "overruled": agent.overruled / max(agent.decisions, 1),
                "minutes": (time.time() - started) / 60,
            }), flush=True)


if __name__ == "__main__":
    main()
