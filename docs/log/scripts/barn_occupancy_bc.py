"""Gauge: a student shaped for the planner's computation. The current scan drawn as an egocentric
occupancy image (CELLS x CELLS cells of CELL_M, the robot at the centre, heading along +x), 2-D
convolutions over it, the target's features beside them, three logits; behaviour cloning offline
on stored DAgger rounds, judged like `barn_offline_bc.py` (agreement with the planner along its
own paths and along the shipped network's in 128 validation caves, /tmp/g/valset), then, with
`closed=N`, driven (turns committed) in N validation caves.

    .venv/bin/python docs/log/scripts/barn_occupancy_bc.py data=RUN[,RUN...] iters=4000 [seed=0] [cells=64] [cell=0.1] [closed=512] [save=F.pt]
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional

from qnav.contracts.actions import TurnCommitment
from qnav.contracts.motion import Outcome
from qnav.contracts.observation import encode_target, target_features
from qnav.sim.evaluate import EvalSettings, episode_outcomes
from qnav.training.episode_log import read_rounds
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import read_settings

CELLS, CELL_M = 64, 0.1
torch.set_num_threads(1)


def images(ranges_m: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(N, 1, CELLS, CELLS) occupancy of the scans (N, B) in metres."""
    n = ranges_m.shape[0]
    x, y = ranges_m * np.cos(angles), ranges_m * np.sin(angles)
    ix = np.floor(x / CELL_M + CELLS / 2).astype(np.int64)
    iy = np.floor(y / CELL_M + CELLS / 2).astype(np.int64)
    ok = np.isfinite(ranges_m) & (ix >= 0) & (ix < CELLS) & (iy >= 0) & (iy < CELLS)
    grid = np.zeros((n, 1, CELLS, CELLS), dtype=np.float32)
    rows = np.broadcast_to(np.arange(n)[:, None], ix.shape)
    grid[rows[ok], 0, ix[ok], iy[ok]] = 1.0
    return grid


class Student(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv2d(1, 16, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=2, padding=1), nn.ReLU(),
        )
        self.head = nn.Sequential(nn.Linear(64 * (CELLS // 16) ** 2 + 3, 256), nn.ReLU(), nn.Linear(256, 3))

    def forward(self, grid: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([self.conv(grid).flatten(1), target], 1))


def inputs(data: EpisodeReplay, now: np.ndarray, angles: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    ranges = data.scan[now].astype(np.float64) * data.max_range_m
    ranges[ranges >= data.max_range_m * 0.999] = np.inf
    target = encode_target(target_features(data.pose[now], data.own_target[now]), data.max_range_m)
    return torch.from_numpy(images(ranges, angles)), torch.from_numpy(target.astype(np.float32))


class Driver:
    """The student driving N worlds, turns committed."""

    def __init__(self, net: Student, angles: np.ndarray, streams: int, max_range_m: float) -> None:
        self.net, self.angles, self.max_range_m = net, angles, max_range_m
        self.turns = TurnCommitment(streams)

    def start(self, worlds, episodes) -> None:  # type: ignore[no-untyped-def]
        self.turns.restart(worlds)

    def act(self, observation):  # type: ignore[no-untyped-def]
        ranges = np.where(observation.scan_m > self.max_range_m, np.inf, observation.scan_m)
        target = encode_target(observation.target_features(), self.max_range_m).astype(np.float32)
        with torch.no_grad():
            logits = self.net(torch.from_numpy(images(ranges.astype(np.float64), self.angles)), torch.from_numpy(target))
        return self.turns(logits.argmax(1).numpy())


def main() -> None:
    global CELLS, CELL_M
    args = dict(a.split("=", 1) for a in sys.argv[1:])
    CELLS, CELL_M = int(args.get("cells", CELLS)), float(args.get("cell", CELL_M))
    runs = [Path(r) for r in args["data"].split(",")]
    iters, lr, batch = int(args.get("iters", 4000)), float(args.get("lr", 5e-4)), 256
    world = read_settings(runs[0]).world
    angles = world.lidar.beam_angles_rad()  # type: ignore[union-attr]

    def replay_of(episodes, w):  # type: ignore[no-untyped-def]
        data = EpisodeReplay(w, sum(len(e.action) + 1 for e in episodes) + 10, 1)
        for e in episodes:
            data.add(e)
        return data

    val_world = replace(world, layout=replace(world.layout, split="validation", worlds=128, order="cycle"))
    vr = read_rounds(Path("/tmp/g/valset"))
    val_own, val_expert = replay_of(vr[0], val_world), replay_of(vr[1], val_world)
    data = replay_of([e for r in runs for rnd in read_rounds(r / "imitation")[:10] for e in rnd], world)
    stored = data.transitions()
    print(f"data: {stored.size} windows", flush=True)
    torch.manual_seed(int(args.get("seed", 0)))
    net = Student()
    opt = torch.optim.Adam(net.parameters(), lr=lr)

    def score(d: EpisodeReplay, n: int = 12000) -> tuple[float, float]:
        now = np.random.default_rng(1).choice(d.transitions(), min(n, d.transitions().size), replace=False)
        net.eval()
        with torch.no_grad():
            logits = torch.cat([net(*inputs(d, c, angles)) for c in np.array_split(now, 12)])
        net.train()
        lab = torch.from_numpy(d.action[now])
        return float((logits.argmax(1) == lab).float().mean()), float(functional.cross_entropy(logits, lab))

    rng = np.random.default_rng(int(args.get("seed", 0)))
    started = time.perf_counter()
    for it in range(1, iters + 1):
        now = stored[rng.integers(0, stored.size, batch)]
        loss = functional.cross_entropy(net(*inputs(data, now, angles)), torch.from_numpy(data.action[now]))
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % 1000 == 0 or it == iters:
            tr, vo, ve = score(data), score(val_own), score(val_expert)
            print(f"it={it} {time.perf_counter() - started:.0f}s train acc={tr[0]:.3f} ce={tr[1]:.3f} | val own acc={vo[0]:.3f}"
                  f" ce={vo[1]:.3f} | val planner-path acc={ve[0]:.3f} ce={ve[1]:.3f}", flush=True)
    if "save" in args:
        torch.save(net.state_dict(), args["save"])
    closed = int(args.get("closed", 0))
    if closed:
        net.eval()
        test = replace(world, layout=replace(world.layout, split="validation", worlds=closed, order="cycle"))
        outcomes, _ = episode_outcomes(test, Driver(net, angles, min(64, closed), data.max_range_m), EvalSettings(episodes=closed, num_worlds=min(64, closed), seed=0))  # type: ignore[arg-type]
        shares = [np.mean(outcomes == k) for k in (Outcome.SUCCESS, Outcome.COLLISION, Outcome.RUNNING)]
        print(f"closed loop, {closed} validation caves: success {shares[0]:.3f} collision {shares[1]:.3f} timeout {shares[2]:.3f}", flush=True)


if __name__ == "__main__":
    main()
