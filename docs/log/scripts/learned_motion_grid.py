# Ad hoc measurement of issue 19 (2026-12-06, session 23).
"""The learned motion perceiver of learned_motion.py, with the scans drawn on a grid.

learned_motion.py reads the five aligned scans as 1-d signals over the beams: an obstacle's
motion there is a shift whose size in beams depends on its range, and its fit crawled (0.76 m/s
per obstacle after 8 passes, no motion 1.00). On a grid in the newest robot's frame (the way
motion-forecasting networks for lidar read it) a motion is the same shift everywhere, which a
small 2-d convolution learns once. Same windows, same labels, same judge (per obstacle, the mean
over its beams of the velocity the network gives the cell each beam's newest return falls in).

Usage: learned_motion_grid.py SCENARIO TRAIN_WINDOWS EPOCHS OUT.pt [--lr L] [--frames K]
[--subcell] [--decay] [--fine]
(--frames: the newest scans the network reads, 5 by default; 1 is its one-frame twin;
--subcell: each cell also carries where in it its returns fall; --decay: the learning rate falls
to zero over the passes, cosine; --fine: velocities on 0.2 m cells instead of 0.4 m)
   or: learned_motion_grid.py --anatomy SCENARIO OUT.pt
(a saved network's held-out errors by range, by beams and by bounces, its speeds against
the true, and its time per window on one thread)
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
import torch
from learned_motion import (
    CLIP_M,
    WINDOW,
    collect,
    per_obstacle_error,
    predictions,
    report,
    training_and_held_out,
)

from qnav.sim.config import scenario

CELL_M = 0.1
HALF_M = 6.4
SIDE = int(2 * HALF_M / CELL_M)  # 128 cells
BEAMS = 720


def cells(aligned_m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(N, K, B) aligned ranges -> (N, K, B) flat cell index of each return on the grid,
    (N, K, B) whether it falls on the grid at all, and (N, K, B, 2) where in its cell (-0.5 to
    0.5 of a cell each way from the centre)."""
    angles = torch.arange(BEAMS, dtype=torch.float32) * (2 * math.pi / BEAMS)
    x = (aligned_m * torch.cos(angles) + HALF_M) / CELL_M
    y = (aligned_m * torch.sin(angles) + HALF_M) / CELL_M
    ix, iy = torch.floor(x).long(), torch.floor(y).long()
    inside = (aligned_m < CLIP_M - 1e-3) & (ix >= 0) & (ix < SIDE) & (iy >= 0) & (iy < SIDE)
    offset = torch.stack([x - ix - 0.5, y - iy - 0.5], dim=-1)
    return (iy.clamp(0, SIDE - 1) * SIDE + ix.clamp(0, SIDE - 1)), inside, offset


def grids(index: torch.Tensor, inside: torch.Tensor, offset: torch.Tensor | None) -> torch.Tensor:
    """(N, K, B) cell indices -> (N, K, SIDE, SIDE) 0/1 grids; with `offset`, (N, 3K, SIDE,
    SIDE): each frame's grid and its returns' mean place in each cell (x, y)."""
    n, k, _ = index.shape
    hit = inside.float()
    grid = torch.zeros(n, k, SIDE * SIDE).scatter_(2, index, hit)
    if offset is None:
        return grid.view(n, k, SIDE, SIDE)
    count = torch.zeros(n, k, SIDE * SIDE).scatter_add_(2, index, hit).clamp(min=1)
    places = [
        torch.zeros(n, k, SIDE * SIDE).scatter_add_(2, index, offset[..., axis] * hit) / count
        for axis in (0, 1)
    ]
    return torch.cat([grid, *places], dim=1).view(n, 3 * k, SIDE, SIDE)


class GridMotionNetwork(torch.nn.Module):
    """Five occupancy grids (0.1 m) -> a velocity field (forward, left; m/s) on 0.4 m cells
    (0.2 m with `fine_output`)."""

    def __init__(
        self,
        frames: int = WINDOW,
        subcell: bool = False,
        fine_output: bool = False,
        width: int = 32,
    ) -> None:
        super().__init__()
        self.stem = torch.nn.Conv2d(
            frames * (3 if subcell else 1), width // 2, 5, stride=2, padding=2
        )  # 0.2 m
        self.fine = torch.nn.Conv2d(width // 2, width // 2, 3, padding=1)
        # 0.4 m cells, or 0.2 m with fine_output
        self.down = torch.nn.Conv2d(width // 2, width, 3, stride=1 if fine_output else 2, padding=1)
        self.shrink = 2 if fine_output else 4
        self.blocks = torch.nn.ModuleList(
            torch.nn.Conv2d(width, width, 3, padding=d, dilation=d) for d in (1, 2, 4, 1)
        )
        self.head = torch.nn.Conv2d(width, 2, 1)
        self.frames = frames
        self.subcell = subcell

    def forward(self, grids: torch.Tensor) -> torch.Tensor:
        x = torch.relu(self.stem(grids))
        x = x + torch.relu(self.fine(x))
        x = torch.relu(self.down(x))
        for block in self.blocks:
            x = x + torch.relu(block(x))
        return self.head(x)  # (N, 2, SIDE / shrink, SIDE / shrink)


def per_beam(network: GridMotionNetwork, aligned_m: torch.Tensor) -> torch.Tensor:
    """(N, K, B) aligned ranges -> (N, B, 2): the velocity at each newest return's cell."""
    index, inside, offset = cells(aligned_m[:, -network.frames :])
    field = network(grids(index, inside, offset if network.subcell else None))
    newest = index[:, -1]
    shrink = network.shrink
    coarse = (newest // SIDE // shrink) * (SIDE // shrink) + (newest % SIDE) // shrink
    flat = field.flatten(2)  # (N, 2, cells)
    return torch.gather(flat, 2, coarse[:, None].expand(-1, 2, -1)).transpose(1, 2)


def load(path: str) -> GridMotionNetwork:
    """A network saved by `main`."""
    saved = torch.load(path)
    network = GridMotionNetwork(
        frames=saved["frames"], subcell=saved["subcell"], fine_output=saved.get("fine", False)
    )
    network.load_state_dict(saved["state"])
    return network.eval()


def anatomy(name: str, path: str) -> None:
    """Where a saved network's errors are, on the held-out windows."""
    network = load(path)
    hx, hy, hidx, turned = collect(scenario(name), 2000, seed=1005, with_turns=True)
    held = predictions(lambda windows: per_beam(network, windows), hx)
    rows = []
    for w in range(len(hidx)):
        for m in np.unique(hidx[w][hidx[w] >= 0]):
            beams = hidx[w] == m
            predicted, true = held[w][beams].mean(0), hy[w][beams][0].astype(np.float64)
            error = np.linalg.norm(predicted - true)
            ratio = np.linalg.norm(predicted) / max(np.linalg.norm(true), 1e-6)
            rows.append((error, ratio, np.median(hx[w, -1][beams]), beams.sum(), turned[w, m]))
    error, ratio, range_m, beams, bounced = np.array(rows).T
    print(f"{len(rows)} obstacles: median {np.median(error):.3f} p90 {np.quantile(error, 0.9):.3f}")
    print(f"predicted speed / true speed, median {np.median(ratio):.3f}")
    for low, high in ((0, 1.5), (1.5, 3), (3, 5)):
        k = (range_m >= low) & (range_m < high)
        print(f"{low}-{high} m: {k.sum()} obstacles, median {np.median(error[k]):.3f}")
    for part, k in (("bounced within the window", bounced > 0), ("straight", bounced == 0)):
        median, p90 = np.median(error[k]), np.quantile(error[k], 0.9)
        print(f"{part}: {k.sum()} obstacles, median {median:.3f} p90 {p90:.3f}")
    for low, high in ((0, 10), (10, 30), (30, 721)):
        k = (beams >= low) & (beams < high)
        print(f"{low}-{high - 1} beams: {k.sum()} obstacles, median {np.median(error[k]):.3f}")
    torch.set_num_threads(1)
    one = torch.from_numpy(hx[:1]).float()
    times_ms = []
    with torch.no_grad():
        for _ in range(60):
            started = time.perf_counter()
            per_beam(network, one)
            times_ms.append(1000 * (time.perf_counter() - started))
    weights = sum(p.numel() for p in network.parameters())
    print(
        f"one window, one thread: median {np.median(times_ms[10:]):.1f} ms, "
        f"p99 {np.quantile(times_ms[10:], 0.99):.1f} ms; {weights} weights"
    )


def main() -> None:
    torch.set_num_threads(2)
    if sys.argv[1] == "--anatomy":
        anatomy(sys.argv[2], sys.argv[3])
        return
    parser = argparse.ArgumentParser()
    parser.add_argument("scenario")
    parser.add_argument("windows", type=int)
    parser.add_argument("epochs", type=int)
    parser.add_argument("out")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--frames", type=int, default=WINDOW)
    parser.add_argument("--subcell", action="store_true")
    parser.add_argument("--decay", action="store_true")
    parser.add_argument("--fine", action="store_true")
    args = parser.parse_args()
    count, epochs = args.windows, args.epochs
    world = scenario(args.scenario)
    started = time.time()
    (x, y, idx), (hx, hy, hidx) = training_and_held_out(world, count)
    torch.manual_seed(0)
    network = GridMotionNetwork(frames=args.frames, subcell=args.subcell, fine_output=args.fine)
    optimizer = torch.optim.Adam(network.parameters(), lr=args.lr)
    total_steps = epochs * math.ceil(count / 64)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer,
        lambda step: 0.5 * (1 + math.cos(math.pi * step / total_steps)) if args.decay else 1.0,
    )
    order = np.random.default_rng(0)
    batch = 64
    for epoch in range(1, epochs + 1):
        perm = order.permutation(len(x))
        network.train()
        total = 0.0
        steps = 0
        for start in range(0, len(x), batch):
            rows = perm[start : start + batch]
            aligned = torch.from_numpy(x[rows]).float()
            target = torch.from_numpy(y[rows]).float()
            weight = torch.from_numpy(idx[rows] >= 0).float()[..., None]
            inside = cells(aligned)[1][:, -1].float()[..., None]
            weight = weight * inside
            predicted = per_beam(network, aligned)
            loss = ((predicted - target) ** 2 * weight).sum() / weight.sum().clamp(min=1)
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            schedule.step()
            total += loss.item()
            steps += 1
            if epoch == 1 and steps == 20:
                print(f"20 steps in {time.time() - started:.0f} s", flush=True)
        network.eval()
        held = predictions(lambda windows: per_beam(network, windows), hx)
        report(epoch, total / steps, per_obstacle_error(held, hy.astype(np.float32), hidx), started)
        saved = {
            "frames": args.frames,
            "subcell": args.subcell,
            "fine": args.fine,
            "state": network.state_dict(),
        }
        torch.save(saved, args.out)


if __name__ == "__main__":
    main()
