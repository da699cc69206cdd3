"""Gauge: does the imitation learner fail to fit the planner, or fit it and not generalise?
Accuracy / cross-entropy of the network against the planner's labels on (a) the run's own
training windows and (b) fresh validation-world episodes the network drives greedily, labelled
by the planner.

    .venv/bin/python docs/log/scripts/barn_imitation_gap.py RUN WORLDS [WEIGHTS=best.pt]
"""
from __future__ import annotations
import sys
from dataclasses import replace
from pathlib import Path
import numpy as np
import torch
from torch.nn import functional
from qnav.sim.mapplan import MapPlanner
from qnav.training.agent import policy_agent
from qnav.training.collect import collect_round
from qnav.training.episode_log import read_rounds
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import load_network

def fit(network, data, now, label=""):
    out = []
    with torch.no_grad():
        for chunk in np.array_split(now, max(1, now.size // 2048)):
            logits = network(torch.from_numpy(data.windows(chunk)))
            out.append(logits)
    logits = torch.cat(out)
    labels = torch.from_numpy(data.action[now])
    ce = float(functional.cross_entropy(logits, labels))
    acc = float((logits.argmax(1) == labels).float().mean())
    return acc, ce

def report(name, network, data, rng, n=20000):
    now = data.transitions()
    if now.size > n:
        now = rng.choice(now, n, replace=False)
    clear = data.clearance[now] if hasattr(data, "clearance") else None
    acc, ce = fit(network, data, now)
    line = f"{name:<28} n={now.size:6d} acc={acc:.3f} ce={ce:.3f}"
    if clear is not None:
        near = clear < 0.3
        a1, c1 = fit(network, data, now[near]) if near.any() else (float('nan'),)*2
        a2, c2 = fit(network, data, now[~near])
        line += f" | near({near.mean():.2f}) acc={a1:.3f} ce={c1:.3f} | far acc={a2:.3f} ce={c2:.3f}"
    print(line, flush=True)

def main():
    run = Path(sys.argv[1]); worlds = int(sys.argv[2]); weights = sys.argv[3] if len(sys.argv) > 3 else "best.pt"
    network, settings = load_network(run, run / weights)
    world = settings.world
    window = settings.train.window
    rng = np.random.default_rng(0)
    rounds = read_rounds(run / "imitation")
    train = EpisodeReplay(world, sum(len(e.action)+1 for r in rounds for e in r) + 10, window)
    for r in rounds:
        for e in r:
            train.add(e)
    report("train (all rounds)", network, train, rng)
    last = EpisodeReplay(world, sum(len(e.action)+1 for e in rounds[-1]) + 10, window)
    for e in rounds[-1]:
        last.add(e)
    report("train (last round)", network, last, rng)
    val_world = replace(world, layout=replace(world.layout, split="validation", worlds=worlds, order="cycle"))
    expert = MapPlanner(val_world)
    agent = policy_agent(network, val_world, worlds, window)
    eps = collect_round(val_world, agent, 0, np.arange(worlds, dtype=np.int64), labeller=lambda s: expert.act_at(s.pose, s.layout))
    outcomes = np.bincount([e.outcome for e in eps], minlength=4)
    print("validation outcomes", outcomes.tolist())
    val = EpisodeReplay(val_world, sum(len(e.action)+1 for e in eps) + 10, window)
    for e in eps:
        val.add(e)
    report("validation (own path)", network, val, rng)

main()
