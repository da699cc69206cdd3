# Ad hoc measurement of issue 19 (2026-12-06, session 22).
"""Can a learned memory of the last five scans perceive the obstacles' motion well enough for
the controller's forecast? The shield's forecast on the tracker's velocities gets 0.90, on one
frame's positions (velocities zero) 0.63 (shield_rule.py's "still:" prefix): the memory of
motion is what dodges. The tracker's memory is hand-built; this fits a network that reads the
motion from a window of five scans, the paper's window, and judges it in the tracker's terms.

The network: the earlier four scans are re-projected into the newest scan's frame (the car's
poses known, as on the car: motion capture), the five aligned scans are channels of circular
1-d convolutions over the beams (dilated to see ~130 beams each way), and each beam predicts the
velocity, in the robot's frame, of the obstacle its return falls on. Labels are free from the
simulator. A one-frame network cannot do better than the mean velocity, which is the baseline.

Usage: learned_motion.py SCENARIO TRAIN_WINDOWS EPOCHS OUT.pt [LEARNING_RATE]
(fits and judges after every pass, saving the network; the learning rate defaults to 1e-3)
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable

import numpy as np
import torch
from numpy.typing import NDArray

from qnav.sim.config import WorldConfig, scenario
from qnav.sim.evaluate import WanderingGoToTarget
from qnav.sim.world import BatchedWorld, observe

WINDOW = 5
CLIP_M = 10.0  # the arena's side: farther returns went out through an opening


def reproject(scans: NDArray, poses: NDArray, angles: NDArray) -> NDArray[np.float32]:
    """(N, K, B) scans taken at (N, K, 3) poses -> (N, K, B) the same returns seen from the
    last pose (the nearest return per beam; CLIP_M where none falls)."""
    n, k, b = scans.shape
    out = np.full((n, k, b), CLIP_M, dtype=np.float64)
    step = 2 * math.pi / b
    now = poses[:, -1]
    for j in range(k):
        ok = np.isfinite(scans[:, j]) & (scans[:, j] < CLIP_M)
        r = np.where(ok, scans[:, j], 0.0)
        heading = poses[:, j, 2:3] + angles[None]
        px = poses[:, j, 0:1] + r * np.cos(heading) - now[:, 0:1]
        py = poses[:, j, 1:2] + r * np.sin(heading) - now[:, 1:2]
        c, s = np.cos(now[:, 2:3]), np.sin(now[:, 2:3])
        fx, fy = c * px + s * py, -s * px + c * py
        beam = np.round(np.arctan2(fy, fx) / step).astype(np.int64) % b
        dist = np.hypot(fx, fy)
        rows = np.broadcast_to(np.arange(n)[:, None], (n, b))
        flat = (rows * k + j) * b + beam
        np.minimum.at(out.reshape(-1), flat[ok], dist[ok])
    return out.astype(np.float32)


def beam_labels(
    world: WorldConfig, pose: NDArray, scan: NDArray, obstacle_xy: NDArray, velocity: NDArray
) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """(N, B) index of the obstacle each beam's return falls on (-1: none), and (N, M, 2) the
    obstacles' velocities in the robot's frame (forward, left)."""
    angles = world.lidar.beam_angles_rad()
    heading = pose[:, 2:3] + angles[None]
    hx = pose[:, 0:1] + scan * np.cos(heading)
    hy = pose[:, 1:2] + scan * np.sin(heading)
    gap = np.hypot(
        hx[:, :, None] - obstacle_xy[:, None, :, 0], hy[:, :, None] - obstacle_xy[:, None, :, 1]
    )
    on = np.abs(gap - world.obstacles.radius_m) < 1e-3
    index = np.where(on.any(axis=2) & np.isfinite(scan), gap.argmin(axis=2), -1)
    c, s = np.cos(pose[:, 2])[:, None], np.sin(pose[:, 2])[:, None]
    vx, vy = velocity[..., 0], velocity[..., 1]
    robot = np.stack([c * vx + s * vy, -s * vx + c * vy], axis=-1)
    return index, robot.astype(np.float32)


def aligned(scans: NDArray, poses: NDArray, angles: NDArray) -> NDArray[np.float16]:
    """A window as the networks here read it: the scans re-projected into the newest frame."""
    return reproject(scans, poses, angles).astype(np.float16)


def collect(world: WorldConfig, count: int, seed: int, with_turns: bool = False, window_of=aligned):  # type: ignore[no-untyped-def]
    """`count` windows with some obstacle return within 5 m: inputs (count, K, B) float16 (or
    what `window_of(scans, poses, beam_angles)` makes of them),
    per-beam targets (count, B, 2) float16 and mask (count, B) bool, plus per-window obstacle
    index per beam for per-obstacle judging; `with_turns`: also (count, M) whether each
    obstacle's velocity changed within the window (a bounce)."""
    worlds = 200
    batched = BatchedWorld(world, worlds, seed=seed)
    observation = observe(world, batched.state)
    driver = WanderingGoToTarget(worlds, 0.3, seed)
    angles = world.lidar.beam_angles_rad()
    scans = np.repeat(observation.scan_m[:, None], WINDOW, axis=1)
    poses = np.repeat(observation.pose[:, None], WINDOW, axis=1)
    velocities = np.repeat(batched.state.obstacle_velocity[:, None], WINDOW, axis=1)
    age = np.zeros(worlds, dtype=np.int64)
    inputs, targets, index_kept, turns = [], [], [], []
    found = 0
    while found < count:
        full = age >= WINDOW - 1
        state = batched.state
        index, robot_v = beam_labels(
            world, observation.pose, observation.scan_m, state.obstacle_xy, state.obstacle_velocity
        )
        near = (index >= 0) & (observation.scan_m < 5.0)
        keep = np.flatnonzero(full & near.any(axis=1))
        if keep.size:
            inputs.append(window_of(scans[keep], poses[keep], angles))
            rows = index[keep]
            v = np.take_along_axis(robot_v[keep], np.maximum(rows, 0)[..., None], axis=1)
            targets.append(np.where(rows[..., None] >= 0, v, 0).astype(np.float16))
            index_kept.append(np.where(near[keep], rows, -1).astype(np.int8))
            change = np.abs(velocities[keep] - velocities[keep][:, -1:]).max(axis=(1, 3))
            turns.append(change > 1e-9)
            found += keep.size
        result = batched.step(driver(observation.target_features()))
        observation = result.observation
        done = result.transition.terminated | result.transition.truncated
        scans = np.concatenate([scans[:, 1:], observation.scan_m[:, None]], axis=1)
        poses = np.concatenate([poses[:, 1:], observation.pose[:, None]], axis=1)
        now_v = batched.state.obstacle_velocity[:, None]
        velocities = np.concatenate([velocities[:, 1:], now_v], axis=1)
        age += 1
        for row in np.flatnonzero(done):  # a fresh episode: its window starts again
            scans[row] = observation.scan_m[row]
            poses[row] = observation.pose[row]
            velocities[row] = now_v[row]
            age[row] = 0
    kept = (
        np.concatenate(inputs)[:count],
        np.concatenate(targets)[:count],
        np.concatenate(index_kept)[:count],
    )
    return (*kept, np.concatenate(turns)[:count]) if with_turns else kept


class MotionNetwork(torch.nn.Module):
    """Five aligned scans -> each beam's obstacle velocity (forward, left) in m/s."""

    def __init__(self, frames: int = WINDOW, width: int = 48) -> None:
        super().__init__()

        def conv(i: int, o: int, k: int, d: int = 1) -> torch.nn.Conv1d:
            return torch.nn.Conv1d(
                i, o, k, padding=d * (k // 2), dilation=d, padding_mode="circular"
            )

        self.stem = conv(3 * frames - 1, width, 5)
        self.blocks = torch.nn.ModuleList(
            conv(width, width, 3, d) for d in (1, 2, 4, 8, 16, 32, 64)
        )
        self.head = torch.nn.Conv1d(width, 2, 1)
        self.frames = frames

    def forward(self, aligned_m: torch.Tensor) -> torch.Tensor:
        """(N, K, B) aligned ranges (m) -> (N, B, 2)."""
        near = 1.0 / aligned_m.clamp(min=0.3)  # near returns matter most
        change = aligned_m[:, -1:] - aligned_m[:, :-1]  # each earlier scan's difference
        x = torch.relu(self.stem(torch.cat([near, aligned_m / CLIP_M, change.clamp(-2, 2)], dim=1)))
        for block in self.blocks:
            x = x + torch.relu(block(x))
        return self.head(x).transpose(1, 2)


def per_obstacle_error(predicted: NDArray, targets: NDArray, index: NDArray) -> NDArray[np.float64]:
    """Error (m/s) of each (window, obstacle)'s mean predicted velocity over its beams."""
    errors = []
    for w in range(len(index)):
        for m in np.unique(index[w][index[w] >= 0]):
            beams = index[w] == m
            errors.append(float(np.linalg.norm(predicted[w][beams].mean(0) - targets[w][beams][0])))
    return np.array(errors)


def predictions(predict: Callable[[torch.Tensor], torch.Tensor], windows: NDArray) -> NDArray:
    """(N, B, 2) `predict`'s velocities for (N, K, B) windows, 256 at a time, without gradients."""
    with torch.no_grad():
        chunks = [
            predict(torch.from_numpy(windows[s : s + 256]).float())
            for s in range(0, len(windows), 256)
        ]
    return torch.cat(chunks).numpy()


def report(epoch: int, loss: float, error: NDArray, started: float) -> None:
    """Print a pass's mean training loss and held-out per-obstacle error."""
    print(
        f"epoch {epoch}: loss {loss:.4f}, held-out per obstacle "
        f"median {np.median(error):.3f} p90 {np.quantile(error, 0.9):.3f} m/s "
        f"({time.time() - started:.0f} s)",
        flush=True,
    )


def training_and_held_out(world: WorldConfig, count: int, window_of=aligned):  # type: ignore[no-untyped-def]
    """`count` training windows and 2,000 held-out ones (other layouts), each as `collect`
    gives them, printing how long they took and the one-frame baseline's error."""
    started = time.time()
    train = collect(world, count, seed=5, window_of=window_of)
    hx, hy, hidx = collect(world, 2000, seed=1005, window_of=window_of)
    print(f"collected {count} + {len(hx)} windows in {time.time() - started:.0f} s", flush=True)
    blind = per_obstacle_error(np.zeros_like(hy, dtype=np.float32), hy.astype(np.float32), hidx)
    median, p90 = np.median(blind), np.quantile(blind, 0.9)
    print(f"one frame (zero velocity): median {median:.3f} p90 {p90:.3f}")
    return train, (hx, hy, hidx)


def main() -> None:
    torch.set_num_threads(2)
    name, count, epochs, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    world = scenario(name)
    started = time.time()
    (x, y, idx), (hx, hy, hidx) = training_and_held_out(world, count)
    torch.manual_seed(0)
    network = MotionNetwork()
    optimizer = torch.optim.Adam(
        network.parameters(), lr=float(sys.argv[5]) if len(sys.argv) > 5 else 1e-3
    )
    inputs, targets = torch.from_numpy(x), torch.from_numpy(y)
    mask = torch.from_numpy(idx >= 0)
    order = np.random.default_rng(0)
    for epoch in range(1, epochs + 1):
        network.train()
        total = 0.0
        for start in range(0, len(x), 64):
            rows = slice(start, start + 64)
            predicted = network(inputs[rows].float())
            weight = mask[rows].float()[..., None]
            loss = ((predicted - targets[rows].float()) ** 2 * weight).sum() / weight.sum().clamp(
                min=1
            )
            optimizer.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]
            optimizer.step()
            total += loss.item()
        network.eval()
        error = per_obstacle_error(predictions(network, hx), hy.astype(np.float32), hidx)
        report(epoch, total / math.ceil(len(x) / 64), error, started)
        torch.save(network.state_dict(), out)
        perm = order.permutation(len(x))
        x, y, idx = x[perm], y[perm], idx[perm]
        inputs, targets, mask = torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(idx >= 0)


if __name__ == "__main__":
    main()
