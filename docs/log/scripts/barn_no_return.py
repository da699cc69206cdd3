"""Gauge: where a BARN policy's failed episodes became lost, on generated cave validation worlds
(never BARN's).

    .venv/bin/python docs/log/scripts/barn_no_return.py POLICY.onnx [WORLDS=256] [OUT.npz]

A state is *recoverable* when the planner given the map, driving from it with a fresh step
budget, reaches the goal. For each collision, the *point of no return* is the last recoverable
state before the crash: there the policy took an action that left no recovery, the planner's
label was another (in a deterministic world the planner's own step keeps its success), and the
gauge records which actions would have kept a recovery, how far the planner's wanted heading was
from its forward/turn threshold (a near-tie), the network's preference (softmax of its outputs)
for what it did, the clearance, and how long before the crash it came. For each timeout: whether
the last state is recoverable (the robot was never trapped: it wandered), and the progress along
the planner's cost-to-go (the share of the start's cost left at its best, and at the end).
"""

from __future__ import annotations

import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.sim.config import WorldConfig, scenario
from qnav.sim.mapplan import MapPlanner
from qnav.sim.world import WorldState, concatenate_rows, observe, reset, scatter, step, take_rows
from qnav.stack import file_agent

sys.path.insert(0, str(Path(__file__).parent))
from barn_label_margins import pose_margins  # noqa: E402

BUDGET_STEPS = 500
"""The planner's fresh budget from a state (the test protocol's episode length)."""
COLLISION_LOOKBACK = 60
"""Steps before a crash searched for the point of no return (12 s)."""
NAMES = ("forward", "left", "right")


def run_policy(policy: Path, world: WorldConfig, count: int):  # type: ignore[no-untyped-def]
    """Every episode's states, actions, network preferences and outcome, all worlds together."""
    agent = file_agent(policy, world, count, lookahead=None)
    episodes = np.arange(count, dtype=np.int64)
    state = reset(world, np.zeros(count, dtype=np.int64), episodes)
    observation = observe(world, state)
    agent.start(np.arange(count), episodes)
    states, actions, prefs = [], [], []
    outcome = np.full(count, -1)
    length = np.zeros(count, dtype=np.int64)
    while (outcome < 0).any():
        action = agent.act(observation)
        q = agent.last_q.astype(np.float64)  # type: ignore[attr-defined]
        z = np.exp(q - q.max(axis=1, keepdims=True))
        states.append(take_rows(state, np.arange(count)))
        actions.append(action.copy())
        prefs.append(z / z.sum(axis=1, keepdims=True))
        state, observation, transition = step(world, state, action)
        ended = (transition.terminated | transition.truncated) & (outcome < 0)
        outcome[ended] = transition.outcome[ended]
        length[ended] = state.steps[ended]
    return states, np.array(actions), np.array(prefs), outcome, length


def recoverable(world: WorldConfig, planner: MapPlanner, starts: WorldState) -> NDArray[np.bool_]:
    """Whether the planner reaches the goal from each state with a fresh budget."""
    state = starts._replace(steps=np.zeros_like(starts.steps))
    done = np.zeros(state.steps.shape[0], dtype=bool)
    success = np.zeros_like(done)
    for _ in range(BUDGET_STEPS):
        live = np.flatnonzero(~done)
        if live.size == 0:
            break
        part = take_rows(state, live)
        part, _, transition = step(world, part, planner.act_at(part.pose, part.layout))
        ended = transition.terminated | transition.truncated
        success[live[ended]] = transition.outcome[ended] == Outcome.SUCCESS
        done[live[ended]] = True
        state = scatter(state, live, part)
    return success


def after_each_action(world: WorldConfig, states: WorldState) -> list[WorldState]:
    """Each state advanced one step by each action."""
    n = states.steps.shape[0]
    return [step(world, states, np.full(n, a, dtype=np.int64))[0] for a in range(3)]


def main() -> None:
    policy = Path(sys.argv[1])
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 256
    base = scenario("cave")
    world = replace(
        base,
        max_episode_steps=BUDGET_STEPS,
        layout=replace(base.layout, split="validation", worlds=count, order="cycle"),
    )
    planner = MapPlanner(world)
    started = time.perf_counter()
    states, actions, prefs, outcome, length = run_policy(policy, world, count)
    shares = {k: float(np.mean(outcome == k)) for k in (Outcome.SUCCESS, Outcome.COLLISION)}
    print(f"policy: success {shares[Outcome.SUCCESS]:.3f} collision {shares[Outcome.COLLISION]:.3f}"
          f" ({time.perf_counter() - started:.0f} s)", flush=True)
    collided = np.flatnonzero(outcome == Outcome.COLLISION)
    # every state in the lookback of each collision, one batch
    rows, where = [], []
    for e in collided.tolist():
        for t in range(max(0, length[e] - COLLISION_LOOKBACK), length[e]):
            rows.append(take_rows(states[t], np.array([e])))
            where.append((e, t))
    ok = recoverable(world, planner, concatenate_rows(rows)) if rows else np.zeros(0, bool)
    print(f"recoverability of {len(rows)} states ({time.perf_counter() - started:.0f} s)", flush=True)
    found = {}
    for (e, t), good in zip(where, ok.tolist(), strict=True):
        if good:
            found[e] = t  # the last recoverable step before the crash
    table = []
    points = [(e, t) for e, t in found.items()]
    if points:
        at = concatenate_rows([take_rows(states[t], np.array([e])) for e, t in points])
        keep = [recoverable(world, planner, s) for s in after_each_action(world, at)]
        labels = planner.act_at(at.pose, at.layout)
        for i, (e, t) in enumerate(points):
            did = int(actions[t, e])
            table.append(dict(
                episode=e, before_crash=int(length[e] - t), did=NAMES[did],
                label=NAMES[int(labels[i])], keeps="".join(NAMES[a][0] for a in range(3) if keep[a][i]),
                margin=float(pose_margins(planner, world, at.pose[i : i + 1], int(at.layout[i]))[0]),
                preference=float(prefs[t, e, did]),
                label_preference=float(prefs[t, e, int(labels[i])]),
                clearance=float(observe(world, take_rows(at, np.array([i]))).clearance_m[0]),
                speed=float(at.velocity[i, 0]),
            ))
    print(f"collisions {collided.size}, a point of no return found in {len(table)}"
          f" (none in the last {COLLISION_LOOKBACK} steps: {collided.size - len(table)})")
    for row in table:
        print("  " + " ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    kinds = Counter(f"did {r['did']}, planner {r['label']}" for r in table)
    print("  kinds:", dict(kinds))
    if table:
        for name, values in (("before_crash", [r["before_crash"] for r in table]),
                             ("margin", [r["margin"] for r in table]),
                             ("preference", [r["preference"] for r in table])):
            print(f"  {name}: median {np.median(values):.2f}, quartiles {np.percentile(values, 25):.2f}"
                  f" / {np.percentile(values, 75):.2f}")
    timed_out = np.flatnonzero(outcome == Outcome.RUNNING)
    timeouts(world, planner, states, timed_out, length)
    print(f"done ({time.perf_counter() - started:.0f} s)")


def timeouts(world: WorldConfig, planner: MapPlanner, states: list[WorldState],
             episodes: NDArray[np.intp], length: NDArray[np.int64]) -> None:
    """Whether each timed-out episode ended recoverable, and its progress along the cost-to-go."""
    if episodes.size == 0:
        return
    last = concatenate_rows([take_rows(states[int(length[e]) - 1], np.array([e])) for e in episodes])
    ok = recoverable(world, planner, last)
    print(f"timeouts {episodes.size}, the last state recoverable in {int(ok.sum())}")
    for i, e in enumerate(episodes.tolist()):
        layout = int(states[0].layout[e])  # type: ignore[index]
        grid = planner.grid(layout)
        cost = np.array([grid.at(states[t].pose[e:e + 1, :2])[0] for t in range(int(length[e]))])
        best = int(np.argmin(cost))
        print(f"  episode={e} recoverable={bool(ok[i])} best_share={cost[best] / cost[0]:.2f}"
              f" at_step={best} end_share={cost[-1] / cost[0]:.2f}")


if __name__ == "__main__":
    main()
