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

Session 25: `--attend` reads the same inputs another way (AttentivePointMotionNetwork): the
network only chooses, per frame, how much each point counts, and the obstacle's places and the
velocity through them are computed from the points, so their precision is the points' own;
`--circle` then fits the known radius's circle through the weighted points.

Usage: learned_motion_points.py SCENARIO TRAIN_WINDOWS EPOCHS OUT.pt [--frames 1]
[--queries Q] [--minutes M] [--from SAVED.pt] [--lr L] [--decay] [--attend [--circle]] [--l1]
(Q query returns per training window, 6 by default; --frames 1 is the one-frame twin; the fit
stops after M minutes of passes, if given; --from starts from a saved network; --decay lowers
the learning rate to zero over the EPOCHS passes, cosine)
   or: learned_motion_points.py --anatomy SCENARIO OUT.pt
(a saved network's held-out errors: bounced or straight, by range, by the obstacle's returns)
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import numpy as np
import torch
from learned_motion import WINDOW, collect, report, training_and_held_out
from numpy.typing import NDArray

from qnav.sim.config import WorldConfig, scenario

RADIUS_M = 1.6  # the farthest an obstacle moves in 0.8 s (1.5 m/s) and its radius, and margin
POINTS = 64
WALL_M = 0.03


def raw(scans: NDArray, poses: NDArray, angles: NDArray) -> NDArray[np.float32]:
    """A window kept as taken: (N, K, B + 3) the ranges and, last, the pose of each scan."""
    return np.concatenate([scans, poses], axis=2).astype(np.float32)


def points(window: NDArray, world: WorldConfig) -> tuple[NDArray, NDArray, NDArray]:
    """(N, K, B + 3) raw windows -> (N, K, B, 2) every return in the newest robot's frame,
    (N, K, B) whether it is a return off the walls, and (N, K, 2) where each scan was taken from
    in that frame."""
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
    sx, sy = poses[..., 0] - now[:, None, 0], poses[..., 1] - now[:, None, 1]
    c, s = c[..., 0], s[..., 0]
    sensor = np.stack([c * sx + s * sy, -s * sx + c * sy], axis=-1).astype(np.float32)
    return xy, seen & off_walls, sensor


def patches(
    xy: NDArray, ok: NDArray, sensor: NDArray, window: NDArray, beam: NDArray
) -> tuple[NDArray, NDArray, NDArray]:
    """For query beam `beam` (Q,) of windows `window` (Q,) of `points`' (xy, ok, sensor): the
    offsets (Q, K, P, 2) of each frame's POINTS nearest points within RADIUS_M of the query's
    newest return, (Q, K, P) which are real, and (Q, K, 2) each scan's origin's offset."""
    query = xy[window, -1, beam]  # (Q, 2)
    offsets = xy[window] - query[:, None, None]  # (Q, K, B, 2)
    distance = np.where(ok[window], np.hypot(offsets[..., 0], offsets[..., 1]), np.inf)
    nearest = np.argpartition(distance, POINTS, axis=2)[..., :POINTS]
    chosen = np.take_along_axis(offsets, nearest[..., None], axis=2)
    real = np.take_along_axis(distance, nearest, axis=2) < RADIUS_M
    origin = (sensor[window] - query[:, None]).astype(np.float32)
    return np.where(real[..., None], chosen, 0.0).astype(np.float32), real, origin


def point_network(frames: int, width: int) -> torch.nn.Sequential:
    """The network both perceivers run on each point: its offset (over RADIUS_M) and its
    frame's one-hot -> `width` features."""
    return torch.nn.Sequential(
        torch.nn.Linear(2 + frames, 64),
        torch.nn.ReLU(),
        torch.nn.Linear(64, width),
        torch.nn.ReLU(),
        torch.nn.Linear(width, width),
    )


def encode(
    point: torch.nn.Module, offsets: torch.Tensor, real: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, K, P, 2) offsets, (N, K, P) real -> (N, K, P, W) each point's features and
    (N, K * 2W) each frame's summary, their maximum and mean over its real points (zero for a
    frame with none)."""
    n, k, p, _ = offsets.shape
    frame = torch.eye(k).view(1, k, 1, k).expand(n, k, p, k)
    x = point(torch.cat([offsets / RADIUS_M, frame], dim=-1))
    mask = real[..., None].float()
    top = torch.where(real[..., None], x, torch.full_like(x, -1e4)).amax(dim=2)
    top = torch.where(real.any(dim=2, keepdim=True), top, torch.zeros_like(top))
    mean = (x * mask).sum(dim=2) / mask.sum(dim=2).clamp(min=1)
    return x, torch.cat([top, mean], dim=-1).reshape(n, -1)


class PointMotionNetwork(torch.nn.Module):
    """Per frame, the points around a query (offsets) -> the velocity (forward, left; m/s) of
    the obstacle the query falls on."""

    def __init__(self, frames: int = WINDOW, width: int = 128) -> None:
        super().__init__()
        self.frames = frames
        self.point = point_network(frames, width)
        self.head = torch.nn.Sequential(
            torch.nn.Linear(2 * width * frames, 256),
            torch.nn.ReLU(),
            torch.nn.Linear(256, 256),
            torch.nn.ReLU(),
            torch.nn.Linear(256, 2),
        )

    def forward(
        self, offsets: torch.Tensor, real: torch.Tensor, origin: torch.Tensor
    ) -> torch.Tensor:
        """(N, K, P, 2) offsets (m), (N, K, P) real -> (N, 2); only the newest `frames` (the
        scans' origins unused)."""
        offsets, real = offsets[:, -self.frames :], real[:, -self.frames :]
        return self.head(encode(self.point, offsets, real)[1])


class AttentivePointMotionNetwork(torch.nn.Module):
    """The same inputs (and the scans' origins) -> the same velocity, read so that precision
    comes from the points themselves rather than from a regression: per frame, the query's
    obstacle is placed at a softmax-weighted mean of that frame's points pushed away from the
    scan's origin by a learned distance (the returns lie on the obstacle's near side), and the
    velocity is a least-squares line through the frames' places over their times, each frame
    weighted by a learned gate (to leave out the frames before a bounce), plus a small learned
    correction."""

    def __init__(
        self,
        period_s: float,
        radius_m: float,
        frames: int = WINDOW,
        width: int = 128,
        circle: bool = False,
    ) -> None:
        super().__init__()
        self.frames = frames
        self.radius_m = radius_m
        self.circle = circle  # places refined by a fit of the known radius's circle
        self.point = point_network(frames, width)
        self.context = torch.nn.Sequential(
            torch.nn.Linear(2 * width * frames + 2 * frames, 256),
            torch.nn.ReLU(),
            torch.nn.Linear(256, 128),
            torch.nn.ReLU(),
        )
        self.score = torch.nn.Sequential(
            torch.nn.Linear(width + 128, 128), torch.nn.ReLU(), torch.nn.Linear(128, 1)
        )
        self.push = torch.nn.Linear(128, frames)
        torch.nn.init.zeros_(self.push.weight)
        torch.nn.init.constant_(self.push.bias, radius_m / 2)
        self.gate = torch.nn.Linear(128, frames)  # how much each frame counts in the line
        torch.nn.init.zeros_(self.gate.weight)
        torch.nn.init.constant_(self.gate.bias, 3.0)
        self.correction = torch.nn.Linear(128, 2)
        torch.nn.init.zeros_(self.correction.weight)
        torch.nn.init.zeros_(self.correction.bias)
        self.register_buffer("times_s", period_s * torch.arange(1 - frames, 1, dtype=torch.float32))

    def places(self, offsets: torch.Tensor, real: torch.Tensor, origin: torch.Tensor):  # type: ignore[no-untyped-def]
        """(N, K, 2) where each frame places the query's obstacle, (N, K) whether it saw it,
        and (N, 128) the window's summary."""
        n, k, p, _ = offsets.shape
        x, summary = encode(self.point, offsets, real)
        context = self.context(torch.cat([summary, origin.reshape(n, -1) / RADIUS_M], dim=-1))
        score = self.score(torch.cat([x, context[:, None, None].expand(n, k, p, -1)], dim=-1))
        score = torch.where(real, score[..., 0], torch.full_like(score[..., 0], -1e4))
        weight = torch.softmax(score, dim=2) * real.float()
        centroid = (weight[..., None] * offsets).sum(dim=2)
        away = centroid - origin
        unit = away / away.norm(dim=-1, keepdim=True).clamp(min=1e-6)
        place = centroid + self.push(context)[..., None] * unit
        if self.circle:
            place = self.fit_circle(place, offsets, weight)
        return place, real.any(dim=2), context

    def fit_circle(
        self, centre: torch.Tensor, offsets: torch.Tensor, weight: torch.Tensor
    ) -> torch.Tensor:
        """Gauss-Newton steps from `centre` (N, K, 2) towards the circle of the obstacles'
        known radius through the weighted points (weighted least squares of the radial gaps;
        lightly damped, for the short arcs of far obstacles)."""
        for _ in range(4):
            spoke = offsets - centre[:, :, None]  # (N, K, P, 2)
            length = spoke.norm(dim=-1).clamp(min=1e-6)
            u = spoke / length[..., None]
            gap = length - self.radius_m
            w = weight[..., None, None]
            normal = (w * u[..., :, None] * u[..., None, :]).sum(dim=2)  # (N, K, 2, 2)
            normal = normal + 1e-3 * torch.eye(2)
            rhs = (weight[..., None] * gap[..., None] * u).sum(dim=2)
            a, b, d = normal[..., 0, 0], normal[..., 0, 1], normal[..., 1, 1]
            det = a * d - b * b
            step_x = (d * rhs[..., 0] - b * rhs[..., 1]) / det
            step_y = (a * rhs[..., 1] - b * rhs[..., 0]) / det
            step = torch.stack([step_x, step_y], dim=-1)
            size = step.norm(dim=-1, keepdim=True)  # a poor weighting must not throw it far
            centre = centre + step * (0.1 / size.clamp(min=0.1))
        return centre

    def forward(
        self, offsets: torch.Tensor, real: torch.Tensor, origin: torch.Tensor
    ) -> torch.Tensor:
        """(N, K, P, 2) offsets (m), (N, K, P) real, (N, K, 2) origins -> (N, 2)."""
        offsets, real = offsets[:, -self.frames :], real[:, -self.frames :]
        place, seen, context = self.places(offsets, real, origin[:, -self.frames :])
        used = seen.float() * torch.sigmoid(self.gate(context))
        t = self.times_s[None]
        t_mean = (used * t).sum(1, keepdim=True) / used.sum(1, keepdim=True).clamp(min=1)
        lever = used * (t - t_mean)
        spread = (lever * (t - t_mean)).sum(1, keepdim=True)
        slope = (lever[..., None] * place).sum(1) / spread.clamp(min=1e-6)
        return torch.where(spread > 1e-6, slope, torch.zeros_like(slope)) + self.correction(context)


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


def held_out_error(network: torch.nn.Module, held, world: WorldConfig) -> NDArray:  # type: ignore[no-untyped-def]
    """Per (window, obstacle): the error of the mean velocity over its returns (at most 8,
    evenly spread, for time)."""
    return held_out_errors(network, held, world)[0]


def held_out_errors(network: torch.nn.Module, held, world: WorldConfig):  # type: ignore[no-untyped-def]
    """`held_out_error`'s errors and, for each, its window and obstacle."""
    hx, hy, hidx = held
    errors, keys = [], []
    for start in range(0, len(hx), 100):
        xy, ok, sensor = points(hx[start : start + 100], world)
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
        inputs = [torch.from_numpy(a) for a in patches(xy, ok, sensor, window, beam)]
        with torch.no_grad():
            velocity = network(*inputs).numpy()
        for w in np.unique(window):
            for m in np.unique(idx[w][idx[w] >= 0]):
                on = (window == w) & (idx[w][beam] == m)
                truth = target[w][beam[on][0]]
                errors.append(float(np.linalg.norm(velocity[on].mean(0) - truth)))
                keys.append((start + w, m))
    return np.array(errors), np.array(keys).reshape(-1, 2)


def load(path: str) -> torch.nn.Module:
    """A network saved by `main`."""
    saved = torch.load(path)
    network: torch.nn.Module = (
        AttentivePointMotionNetwork(
            saved["period_s"],
            saved["radius_m"],
            frames=saved["frames"],
            circle=saved.get("circle", False),
        )
        if "period_s" in saved
        else PointMotionNetwork(frames=saved["frames"])
    )
    network.load_state_dict(saved["state"])
    return network.eval()


def track_velocity(
    network: torch.nn.Module, cloud: tuple[NDArray, NDArray, NDArray], row: int, on: NDArray
) -> NDArray:
    """(2,) the mean velocity (forward, left) the network gives the newest returns `on` (beam
    indices) of window `row` (at most 8 of them, evenly spread), from `points`' (xy, ok, sensor)."""
    on = on[np.unique(np.linspace(0, on.size - 1, min(on.size, 8)).round().astype(int))]
    inputs = [torch.from_numpy(a) for a in patches(*cloud, np.full(on.size, row), on)]
    with torch.no_grad():
        return network(*inputs).numpy().mean(0)


def anatomy(name: str, path: str) -> None:
    """Where a saved network's errors are, on the held-out windows: bounced or straight, by
    range and by how many returns the obstacle gives."""
    world = scenario(name)
    hx, hy, hidx, turned = collect(world, 2000, seed=1005, with_turns=True, window_of=raw)
    error, keys = held_out_errors(load(path), (hx, hy, hidx), world)
    on = [hidx[w] == m for w, m in keys]
    bounced = np.array([turned[w, m] for w, m in keys])
    range_m = np.array([np.median(hx[w, -1, :-3][b]) for (w, _), b in zip(keys, on, strict=True)])
    beams = np.array([b.sum() for b in on])
    print(
        f"{len(error)} obstacles: median {np.median(error):.3f} p90 {np.quantile(error, 0.9):.3f}"
    )
    print_anatomy(error, bounced, range_m, beams)


def print_anatomy(
    error: NDArray, bounced: NDArray, range_m: NDArray, returns: NDArray, digits: int = 3
) -> None:
    """Print per-obstacle errors' median and p90 split by bounced or straight, by range and by
    how many returns the obstacle gives (each argument one entry per obstacle)."""
    parts = [("bounced within the window", bounced), ("straight", ~bounced)]
    parts += [
        (f"{lo}-{hi} m", (range_m >= lo) & (range_m < hi))
        for lo, hi in ((0, 1.5), (1.5, 3), (3, 5))
    ]
    parts += [
        (f"{lo}-{hi - 1} returns", (returns >= lo) & (returns < hi))
        for lo, hi in ((0, 10), (10, 30), (30, 721))
    ]
    for part, k in parts:
        median, p90 = np.median(error[k]), np.quantile(error[k], 0.9)
        print(f"{part}: {k.sum()} obstacles, median {median:.{digits}f} p90 {p90:.{digits}f}")


def main() -> None:
    if sys.argv[1] == "--anatomy":
        anatomy(sys.argv[2], sys.argv[3])
        return
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
    parser.add_argument("--attend", action="store_true")
    parser.add_argument("--circle", action="store_true")
    parser.add_argument("--l1", action="store_true")  # the error's length, not its square
    args = parser.parse_args()
    torch.set_num_threads(2)
    world = scenario(args.scenario)
    started = time.time()
    (x, y, idx), held = training_and_held_out(world, args.windows, window_of=raw)
    window, beam = queries(idx, args.queries, seed=0)
    parts = []
    for start in range(0, len(window), 4096):
        rows = window[start : start + 4096]
        first, last = rows.min(), rows.max() + 1
        xy, ok, sensor = points(x[first:last], world)
        parts.append(patches(xy, ok, sensor, rows - first, beam[start : start + 4096]))
    inputs, present, origins = (
        torch.from_numpy(np.concatenate(part)) for part in zip(*parts, strict=True)
    )
    targets = torch.from_numpy(y[window, beam].astype(np.float32))
    del x
    print(f"{len(window)} queries ready ({time.time() - started:.0f} s)", flush=True)
    torch.manual_seed(0)
    kind = {"frames": args.frames}
    if args.start is not None:
        kind = {key: value for key, value in torch.load(args.start).items() if key != "state"}
    elif args.attend:
        kind |= {"period_s": world.control_period_s, "radius_m": world.obstacles.radius_m}
        kind |= {"circle": args.circle}
    network: torch.nn.Module
    if args.start is not None:
        network = load(args.start)
    elif args.attend:
        network = AttentivePointMotionNetwork(
            kind["period_s"], kind["radius_m"], frames=args.frames
        )
    else:
        network = PointMotionNetwork(frames=args.frames)
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
            predicted = network(inputs[rows], present[rows], origins[rows])
            squared = ((predicted - targets[rows]) ** 2).sum(1)
            loss = (squared + 1e-8).sqrt().mean() if args.l1 else squared.mean()
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            schedule.step()
            total, batches = total + loss.item(), batches + 1
        network.eval()
        report(epoch, total / batches, held_out_error(network, held, world), started)
        torch.save(kind | {"state": network.state_dict()}, args.out)
        if time.time() - fitting > 60 * args.minutes:
            break


if __name__ == "__main__":
    main()
