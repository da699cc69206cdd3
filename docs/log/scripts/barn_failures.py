"""Gauge: how a BARN policy file fails, by kind, on generated cave validation worlds (never
BARN's): each failed episode's last steps against the planner given the map.

    .venv/bin/python docs/log/scripts/barn_failures.py POLICY.onnx [WORLDS=128]

Collisions: the action that hit, and whether the planner would have taken another one in the
last 5 steps. Timeouts: how far the robot got in its last 100 steps (stuck: under 0.5 m) and how
often it flipped between left and right turns there (dithering), and the share of its last 100
steps on which the planner agreed.
"""

from __future__ import annotations

import itertools
import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

from qnav.contracts.actions import Action
from qnav.contracts.motion import Outcome
from qnav.sim.config import scenario
from qnav.sim.mapplan import MapPlanner
from qnav.sim.world import observe, reset, step
from qnav.stack import file_agent


def main() -> None:
    policy = Path(sys.argv[1])
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 128
    base = scenario("cave")
    world = replace(
        base, layout=replace(base.layout, split="validation", worlds=count, order="cycle")
    )
    expert = MapPlanner(world)
    kinds: Counter[str] = Counter()
    for episode in range(count):
        agent = file_agent(policy, world, 1, lookahead=None)
        state = reset(world, np.array([0]), np.array([episode]))
        observation = observe(world, state)
        agent.start(np.arange(1), np.array([episode]))
        acts, labels, poses = [], [], []
        while True:
            action = agent.act(observation)
            acts.append(int(action[0]))
            labels.append(int(expert.act(observation)[0]))
            poses.append(state.pose[0, :2].copy())
            state, observation, transition = step(world, state, action)
            if transition.terminated[0] or transition.truncated[0]:
                break
        outcome = int(transition.outcome[0])
        if outcome == Outcome.SUCCESS:
            kinds["success"] += 1
        elif outcome == Outcome.COLLISION:
            last = slice(-5, None)
            differed = any(a != e for a, e in zip(acts[last], labels[last], strict=True))
            hit = Action(acts[-1]).name.lower()
            kinds[f"collision, {hit}, planner {'differed' if differed else 'agreed'}"] += 1
        else:
            tail = np.array(poses[-100:])
            moved = float(np.linalg.norm(tail.max(axis=0) - tail.min(axis=0)))
            turns = [a for a in acts[-100:] if a != Action.FORWARD]
            flips = sum(1 for a, b in itertools.pairwise(turns) if a != b)
            agree = np.mean(np.array(acts[-100:]) == np.array(labels[-100:]))
            where = "stuck" if moved < 0.5 else "moving"
            kinds[f"timeout, {where}, {'dithering' if flips >= 10 else 'steady'}"] += 1
            kinds["timeout agreement x100 (sum)"] += round(100 * agree)
    for kind, n in sorted(kinds.items()):
        print(f"{n:5d}  {kind}")


if __name__ == "__main__":
    main()
