# Ad hoc measurement of issue 19 (2026-12-06, session 24).
"""The learned motion perceiver of learned_motion_grid.py, reading the returns as points.

The grid network's error (0.088 m/s per obstacle) sits on one curve whatever was changed, and
its inputs explain a floor under it: the earlier scans are re-projected onto the newest scan's
beams (0.5 degrees: 2.6 cm sideways at 3 m) and then drawn on 0.1 m cells, while a velocity
within 0.01 m/s over the window's 0.8 s needs the obstacle's places within about a centimetre.
Here nothing is rounded: every return of the five scans is a point in the newest robot's frame
(float32, from the motion-capture poses), returns on the room's known walls are dropped (the
tracker drops them too; the room is known on the car), and for one query return of the newest
scan the network reads, per frame, the P nearest points within R of it (their offsets from the
query) and gives the velocity of the obstacle the query falls on. Per frame a shared point
network pooled by maximum and mean (a set network: the points' order means nothing), then the
five frames' summaries in order to a small head. Same windows, labels and judge as the others
(per obstacle, the mean over its returns' velocities; held out on other layouts).

Usage: learned_motion_points.py SCENARIO TRAIN_WINDOWS EPOCHS OUT.pt [--frames 1]
[--queries Q] [--minutes M] [--from SAVED.pt] [--lr L] [--decay]
(Q query returns per training window, 6 by default; --frames 1 is the one-frame twin; the fit
stops after M minutes of passes, if given; --from starts from a saved network; --decay lowers
the learning rate to zero over the EPOCHS passes, cosine)
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch
from learned_motion import WINDOW, report, training_and_held_out
from numpy.typing import NDArray

from qnav.sim.config import WorldConfig, scenario

RADIUS_M = 1.6  # the farthest an obstacle moves in 0.8 s (1.5 m/s) and its radius, and margin
POINTS = 64
WALL_M = 0.03


def raw(scans: NDArray, poses: NDArray, angles: NDArray) -> NDArray[np.float32]:
    """A window kept as taken: (N, K, B + 3) the ranges and, last, the pose of each scan."""
    return np.concatenate([scans, poses], axis=2).astype(np.float32)


def points(window: NDArray, world: WorldConfig) -> tuple[NDArray, NDArray]:
    """(N, K, B + 3) raw windows -> (N, K, B, 2) every return in the newest robot's frame and
    (N, K, B) whether it is a return off the walls."""
    beams = window.shape[2] - 3
    scans, poses = window[..., :beams].astype(np.float64), window[..., beams:].astype(np.float64)
    heading = poses[..., 2:3] + world.lidar.beam_angles_rad()
    seen = np.isfinite(scans) & (scans < world.lidar.max_range_m)
    r = np.where(seen, scans, 0.0)
    wx = poses[..., 0:1] + r * np.cos(heading)
    wy = poses[..., 1:2] + r * np.sin(heading)
    size = world.arena.size_m
    off_walls = np.minimum(np.minimum(wx, size - wx), np.minimum(wy, size - wy)) > WALL_M
    now = poses[:, -1]
    dx, dy = wx - now[:, None, 0:1], wy - now[:, None, 1:2]
    c, s = np.cos(now[:, 2])[:, None, None], np.sin(now[:, 2])[:, None, None]
    xy = np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1).astype(np.float32)
    return xy, seen & off_walls


def patches(xy: NDArray, ok: NDArray, window: NDArray, beam: NDArray) -> tuple[NDArray, NDArray]:
    """For query beam `beam` (Q,) of windows `window` (Q,) of the points (N, K, B, 2): the
    offsets (Q, K, P, 2) of each frame's POINTS nearest points within RADIUS_M of the query's
    newest return, and (Q, K, P) which are real."""
    query = xy[window, -1, beam]  # (Q, 2)
    offsets = xy[window] - query[:, None, None]  # (Q, K, B, 2)
    distance = np.where(ok[window], np.hypot(offsets[..., 0], offsets[..., 1]), np.inf)
    nearest = np.argpartition(distance, POINTS, axis=2)[..., :POINTS]
    chosen = np.take_along_axis(offsets, nearest[..., None], axis=2)
    real = np.take_along_axis(distance, nearest, axis=2) < RADIUS_M
    return np.where(real[..., None], chosen, 0.0).astype(np.float32), real


class PointMotionNetwork(torch.nn.Module):
    """Per frame, the points around a query (offsets) -> the velocity (forward, left; m/s) of
    the obstacle the query falls on."""

    def __init__(self, frames: int = WINDOW, width: int = 128) -> None:
        super().__init__()
        self.frames = frames
        self.point = torch.nn.Sequential(
            torch.nn.Linear(2 + frames, 64),
            torch.nn.ReLU(),
            torch.nn.Linear(64, width),
            torch.nn.ReLU(),
            torch.nn.Linear(width, width),
        )
        self.head = torch.nn.Sequential(
            torch.nn.Linear(2 * width * frames, 256),
            torch.nn.ReLU(),
            torch.nn.Linear(256, 256),
            torch.nn.ReLU(),
            torch.nn.Linear(256, 2),
        )

    def forward(self, offsets: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
        """(N, K, P, 2) offsets (m), (N, K, P) real -> (N, 2); only the newest `frames`."""
        offsets, real = offsets[:, -self.frames :], real[:, -self.frames :]
        n, k, p, _ = offsets.shape
        frame = torch.eye(k).view(1, k, 1, k).expand(n, k, p, k)
        x = self.point(torch.cat([offsets / RADIUS_M, frame], dim=-1))
        mask = real[..., None].float()
        top = torch.where(real[..., None], x, torch.full_like(x, -1e4)).amax(dim=2)
        top = torch.where(real.any(dim=2, keepdim=True), top, torch.zeros_like(top))
        mean = (x * mask).sum(dim=2) / mask.sum(dim=2).clamp(min=1)
        return self.head(torch.cat([top, mean], dim=-1).reshape(n, -1))


def queries(index: NDArray, per_window: int, seed: int) -> tuple[NDArray, NDArray]:
    """Up to `per_window` random returns on obstacles of each window (N, B): (window, beam)."""
    rng = np.random.default_rng(seed)
    windows, beams = [], []
    for w in range(len(index)):
        on = np.flatnonzero(index[w] >= 0)
        pick = rng.choice(on, size=min(per_window, on.size), replace=False)
        windows.append(np.full(pick.size, w))
        beams.append(pick)
    return np.concatenate(windows), np.concatenate(beams)


def held_out_error(network: PointMotionNetwork, held, world: WorldConfig) -> NDArray:  # type: ignore[no-untyped-def]
    """Per (window, obstacle): the error of the mean velocity over its returns (at most 8,
    evenly spread, for time)."""
    hx, hy, hidx = held
    errors = []
    for start in range(0, len(hx), 100):
        xy, ok = points(hx[start : start + 100], world)
        idx, target = hidx[start : start + 100], hy[start : start + 100].astype(np.float32)
        window, beam = np.nonzero(idx >= 0)
        order = np.argsort(idx[window, beam].astype(np.int64) + 100 * window, kind="stable")
        window, beam = window[order], beam[order]
        _, first, count = np.unique(
            idx[window, beam].astype(np.int64) + 100 * window, return_index=True, return_counts=True
        )
        spread = np.concatenate(
            [
                f + np.unique(np.linspace(0, c - 1, min(c, 8)).round().astype(int))
                for f, c in zip(first, count, strict=True)
            ]
        )
        window, beam = window[spread], beam[spread]
        offsets, real = patches(xy, ok, window, beam)
        with torch.no_grad():
            velocity = network(torch.from_numpy(offsets), torch.from_numpy(real)).numpy()
        for w in np.unique(window):
            for m in np.unique(idx[w][idx[w] >= 0]):
                on = (window == w) & (idx[w][beam] == m)
                truth = target[w][beam[on][0]]
                errors.append(float(np.linalg.norm(velocity[on].mean(0) - truth)))
    return np.array(errors)


def load(path: str) -> PointMotionNetwork:
    """A network saved by `main`."""
    saved = torch.load(path)
    network = PointMotionNetwork(frames=saved["frames"])
    network.load_state_dict(saved["state"])
    return network.eval()


def track_velocity(
    network: PointMotionNetwork, xy: NDArray, ok: NDArray, row: int, on: NDArray
) -> NDArray:
    """(2,) the mean velocity (forward, left) the network gives the newest returns `on` (beam
    indices) of window `row` (at most 8 of them, evenly spread), from `points`' (xy, ok)."""
    on = on[np.unique(np.linspace(0, on.size - 1, min(on.size, 8)).round().astype(int))]
    offsets, real = patches(xy, ok, np.full(on.size, row), on)
    with torch.no_grad():
        return network(torch.from_numpy(offsets), torch.from_numpy(real)).numpy().mean(0)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("scenario")
    parser.add_argument("windows", type=int)
    parser.add_argument("epochs", type=int)
    parser.add_argument("out")
    parser.add_argument("--frames", type=int, default=WINDOW)
    parser.add_argument("--queries", type=int, default=6)
    parser.add_argument("--minutes", type=float, default=math.inf)
    parser.add_argument("--from", dest="start", default=None)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--decay", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(2)
    world = scenario(args.scenario)
    started = time.time()
    (x, y, idx), held = training_and_held_out(world, args.windows, window_of=raw)
    window, beam = queries(idx, args.queries, seed=0)
    offsets, real = [], []
    for start in range(0, len(window), 4096):
        rows = window[start : start + 4096]
        first, last = rows.min(), rows.max() + 1
        xy, ok = points(x[first:last], world)
        part = patches(xy, ok, rows - first, beam[start : start + 4096])
        offsets.append(part[0])
        real.append(part[1])
    inputs, present = (
        torch.from_numpy(np.concatenate(offsets)),
        torch.from_numpy(np.concatenate(real)),
    )
    targets = torch.from_numpy(y[window, beam].astype(np.float32))
    del x
    print(f"{len(window)} queries ready ({time.time() - started:.0f} s)", flush=True)
    torch.manual_seed(0)
    network = PointMotionNetwork(frames=args.frames) if args.start is None else load(args.start)
    optimizer = torch.optim.Adam(network.parameters(), lr=args.lr)
    steps = args.epochs * math.ceil(len(window) / 256)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda k: 0.5 * (1 + math.cos(math.pi * k / steps)) if args.decay else 1.0
    )
    fitting = time.time()
    for epoch in range(1, args.epochs + 1):
        network.train()
        total, batches = 0.0, 0
        for rows in torch.randperm(len(window)).split(256):
            loss = ((network(inputs[rows], present[rows]) - targets[rows]) ** 2).sum(1).mean()
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            schedule.step()
            total, batches = total + loss.item(), batches + 1
        network.eval()
        report(epoch, total / batches, held_out_error(network, held, world), started)
        torch.save({"frames": args.frames, "state": network.state_dict()}, args.out)
        if time.time() - fitting > 60 * args.minutes:
            break


if __name__ == "__main__":
    main()
