"""Gauge: a BARN policy file under a shield that forecasts against the lidar's own points (the
scan's returns, standing still, in the frame of the decision), on generated cave validation
worlds (never BARN's). Each first action is followed by the structured continuations of
`contracts.lookahead` over HORIZON steps of the robot's model; the policy's action stands
unless at least SHARE of its continuations collide, then the best-valued among the least
colliding (`contracts.lookahead.shielded_actions`).

    .venv/bin/python docs/log/scripts/barn_lidar_shield.py POLICY.onnx WORLDS HORIZON,SHARE[,MARGIN] ...

"none" runs the file alone. MARGIN (m) is added to the robot's radius in the forecast.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.lookahead import (
    LookaheadModel,
    ObstacleFutures,
    collision_shares,
    shielded_actions,
    structured_sequences,
)
from qnav.contracts.motion import Outcome, wrap_angle
from qnav.sim.config import WorldConfig, scenario
from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent, episode_outcomes
from qnav.sim.world import Observation
from qnav.stack import file_agent
from qnav.tracking import lidar_of



class Frame(NamedTuple):
    pose: NDArray[np.float64]
    velocity: NDArray[np.float64]
    target_xy: NDArray[np.float64]
    obstacle_xy: NDArray[np.float64]
    obstacle_velocity: NDArray[np.float64]


class LidarShield:
    def __init__(
        self, inner: StreamPolicyAgent, world: WorldConfig, horizon: int, share: float, margin: float
    ) -> None:
        self.inner, self.horizon, self.share = inner, horizon, share
        self.angles = lidar_of(world).beam_angles_rad()
        far = np.array([[1e6, 1e6]])
        self.model = LookaheadModel(
            dynamics=world.dynamics,
            control_period_s=world.control_period_s,
            robot_radius_m=world.robot_radius_m + margin,
            obstacle_radius_m=0.0,
            room_size_m=1e6,
            wall_start=far,
            wall_end=far + 1.0,
        )
        self.period = world.control_period_s
        self.tails = structured_sequences(horizon - 1)
        self.previous: NDArray[np.float64] | None = None
        self.overruled = 0
        # Returns beyond the top speed times the horizon, plus the robot, cannot be met.
        top_mps = world.dynamics.max_speed_mps
        self.reach_m = top_mps * horizon * self.period + self.model.robot_radius_m + 0.1

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        self.inner.start(worlds, episodes)
        if self.previous is not None:
            self.previous[worlds] = np.nan

    def _velocity(self, pose: NDArray[np.float64]) -> NDArray[np.float64]:
        if self.previous is None:
            self.previous = np.full_like(pose, np.nan)
        delta = pose - self.previous
        heading = self.previous[:, 2]
        forward = (delta[:, 0] * np.cos(heading) + delta[:, 1] * np.sin(heading)) / self.period
        turn = wrap_angle(delta[:, 2]) / self.period
        self.previous = pose.copy()
        return np.nan_to_num(np.stack([forward, turn], axis=1))

    def act(self, observation: Observation) -> NDArray[np.int64]:
        actions = self.inner.act(observation)
        scan = observation.scan_m
        assert scan is not None
        velocity = self._velocity(observation.pose)
        n = scan.shape[0]
        near = np.isfinite(scan) & (scan < self.reach_m)
        most = max(1, int(near.sum(axis=1).max()))
        points = np.full((n, most, 2), 1e6)
        for row in range(n):
            ranges, angles = scan[row][near[row]], self.angles[near[row]]
            points[row, : ranges.size] = np.stack([ranges * np.cos(angles), ranges * np.sin(angles)], 1)
        origin = np.zeros((n, 3))
        frame = Frame(origin, velocity, np.full((n, 2), 1e6), points, np.zeros_like(points))
        futures = ObstacleFutures(
            np.broadcast_to(points[None, :, None], (self.horizon, n, 1, most, 2)),
            np.zeros((n, most)),
        )
        tails = np.broadcast_to(self.tails, (n, *self.tails.shape))
        shares = collision_shares(self.model, frame, tails, futures)
        chosen = shielded_actions(self.inner.last_q, shares, self.share, chosen=actions)
        self.overruled += int((chosen != actions).sum())
        return chosen


def main() -> None:
    policy, count = Path(sys.argv[1]), int(sys.argv[2])
    base = scenario("cave")
    world = replace(base, layout=replace(base.layout, split="validation", worlds=count, order="cycle"))
    settings = EvalSettings(episodes=count, num_worlds=64, seed=0)
    for spec in sys.argv[3:]:
        started = time.perf_counter()
        agent = file_agent(policy, world, 64, lookahead=None)
        if spec != "none":
            horizon, share, *margin = spec.split(",")
            agent = LidarShield(agent, world, int(horizon), float(share), float(margin[0]) if margin else 0.0)  # type: ignore[arg-type]
        outcomes, _ = episode_outcomes(world, agent, settings)
        shares = [np.mean(outcomes == k) for k in (Outcome.SUCCESS, Outcome.COLLISION, Outcome.RUNNING)]
        print(
            f"{spec}: success {shares[0]:.3f} collision {shares[1]:.3f} timeout {shares[2]:.3f}"
            f" overruled {getattr(agent, 'overruled', 0)} ({time.perf_counter() - started:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
