# Ad hoc measurement of issue 19 (2026-12-06); runs against commit 0475843 and later.
"""Where the judged DQN's collisions start: for each collision episode, its fatal decision (the
first step where the action taken is truly doomed while another is not), and whether the judge
file thought that action safe, and whether the forecast on the same tracked belief saw it riskier
than another.

Usage: miss_anatomy.py RUN JUDGE_FILE EPISODES
"""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from qnav.controller.lookahead import risks_of, safeties_of
from qnav.controller.perception import TrackerSettings
from qnav.lab.decisive import is_decisive
from qnav.lab.oracle import collision_shares
from qnav.sim.evaluate import EvalResult, EvalSettings, episode_outcomes
from qnav.sim.world import take_rows
from qnav.tracking import LookaheadAgent, lookahead_settings
from qnav.training.agent import policy_agent
from qnav.training.run_folder import load_network


class Recorder:
    def __init__(self, agent, policy, world):  # type: ignore[no-untyped-def]
        self.agent, self.policy, self.world = agent, policy, world
        self.rows: list[dict] = []
        self.episode_of = np.zeros(0, dtype=np.int64)

    def watch(self, state, counting):  # type: ignore[no-untyped-def]
        self.state, self.counting = state, counting.copy()

    def start(self, worlds, episodes):  # type: ignore[no-untyped-def]
        if self.episode_of.size == 0:
            self.episode_of = np.zeros(len(self.agent.cars), dtype=np.int64)
        self.episode_of[worlds] = episodes
        self.agent.start(worlds, episodes)

    def act(self, observation):  # type: ignore[no-untyped-def]
        taken = self.agent.act(observation)
        preferred = self.policy.last_q.argmax(axis=1)
        counted = np.flatnonzero(self.counting)
        truth = collision_shares(self.world, take_rows(self.state, counted))
        targets = list(observation.target_xy)
        cars = [self.agent.cars[i] for i in counted]
        safe = safeties_of(cars, [targets[i] for i in counted])
        risk = risks_of(cars, [targets[i] for i in counted])
        for j, i in enumerate(counted):
            self.rows.append(dict(episode=int(self.episode_of[i]), step=int(self.state.steps[i]),
                                  taken=int(taken[i]), preferred=int(preferred[i]),
                                  truth=truth[j], safe=safe[j], risk=risk[j],
                                  nearest=float(np.min(np.linalg.norm(
                                      self.state.obstacle_xy[i] - self.state.pose[i, :2], axis=1)))))
        return taken


def main() -> None:
    torch.set_num_threads(1)
    run, judge, episodes = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])
    network, folder = load_network(run)
    world = folder.world
    protocol = EvalSettings(episodes=episodes)
    worlds = min(protocol.num_worlds, episodes)
    policy = policy_agent(network, world, worlds, folder.train.window, seed=protocol.seed)
    agent = LookaheadAgent(policy, world, worlds, tracker=TrackerSettings(),
                           lookahead=lookahead_settings("judge", judge), seed=protocol.seed)
    threshold = agent.cars[0].judge.contract.threshold
    recorder = Recorder(agent, policy, world)
    outcomes, steps = episode_outcomes(world, recorder, protocol, watch=recorder.watch)
    result = EvalResult.of_outcomes(outcomes, steps)
    print(f"success {result.success:.3f} over {episodes}; threshold {threshold}")
    by_episode: dict[int, list[dict]] = {}
    for row in recorder.rows:
        by_episode.setdefault(row["episode"], []).append(row)
    kinds: Counter[str] = Counter()
    for episode in np.flatnonzero(outcomes == 2):
        rows = sorted(by_episode.get(int(episode), []), key=lambda r: r["step"])
        fatal = None
        for row in rows:
            doomed = row["truth"] == 1.0
            if doomed[row["taken"]] and is_decisive(doomed[None])[0]:
                fatal = row
                break
        if fatal is None:
            kinds["no decisive fatal step (doomed from its first doomed step, or unlabelled)"] += 1
            continue
        doomed = fatal["truth"] == 1.0
        judge_kept = fatal["taken"] == fatal["preferred"]
        judge_safe = fatal["safe"][fatal["taken"]] >= threshold
        forecast_saw = fatal["risk"][fatal["taken"]] > fatal["risk"].min()
        what = ("judge kept the DQN's doomed action (thought safe)" if judge_kept
                else "judge overruled, into a doomed action")
        kinds[f"{what}; forecast {'saw it riskier' if forecast_saw else 'did not'}"] += 1
        print(f"ep {episode} step {fatal['step']} nearest {fatal['nearest']:.2f} m truth "
              f"{np.round(fatal['truth'], 2)} P(safe) {np.round(fatal['safe'], 2)} forecast "
              f"{np.round(fatal['risk'], 2)} taken {fatal['taken']} preferred {fatal['preferred']}")
    for kind, count in kinds.most_common():
        print(f"{count:4d}  {kind}")


if __name__ == "__main__":
    main()
