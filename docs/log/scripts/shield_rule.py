# Ad hoc measurement of issue 19 (2026-12-06); runs against the commit adding
# lookahead.overrule_share, and later.
"""Which rule should the controller's forecast serve? The shielded DQN (the forecast on the
onboard tracker, `qnav eval --lookahead shield`) takes the DQN's best-valued action among the
least colliding; with exact shares the near-doom rule (keep the DQN's action unless at least q
of its continuations collide, else the least colliding) did better (0.945 against 0.925,
margin_gauge.py). Gauge: the same forecast on the same tracker, only the rule changed.

Usage: shield_rule.py RUN EPISODES SEED RULE[,RULE...]
RULE: "shield" (overrule wherever a safer action exists: the rule before overrule_share),
"tolT" (the shield with tolerance T),
"nearQ" (keep the DQN's action unless its share >= Q, else the least colliding, ties by value:
`lookahead.overrule_share` = Q); a "truth:" prefix
forecasts from the true state instead of the tracker's (`lab.oracle.collision_shares`, the
labels' continuations): what perception costs the rule; an "hS:" prefix forecasts S seconds
ahead instead of `lookahead.shield_horizon_s` (6 s; 4 s before 2026-12-06); a "v0:" prefix
gives the tracks of each episode's first decision (seen once: no velocity yet) the true
velocities; a "restN:" prefix lets each car stand at its start for N control periods before
the episode, its tracker taking the scans there while the obstacles move (the controller's
tracking at rest, 2026-12-06: the obstacles' earlier places are their motion run backwards);
a "still:" prefix forecasts every track standing where it was last seen (velocity zero, the
tracker itself untouched): what a perceiver without memory of earlier frames could give the
forecast; a "smearS:" prefix gives the tracker the scans of a rotating lidar whose turn takes S
seconds and ends at the decision (beam 0 first, in 40 slices of beams, each cast from the car's
pose and the obstacles' places at its time; the car's pose at the decision, as motion capture
gives it, is what the tracker pairs the scan with; the DQN keeps the instantaneous scan); with
an "ego:" prefix beside it only the car moves during the turn (the obstacles stand where they are
at the decision), with "obs:" only the obstacles; a "learned@NETWORK:" prefix forecasts every
track with the velocity a learned motion perceiver (learned_motion_grid.py's saved NETWORK) reads
from the last five (noisy) scans, the mean over the beams that fall on the track (within
radius + 0.15 m of its centre; zero where none do), the tracker's own velocities untouched and
unused: the learned memory in the tracker's place (2026-12-06, session 23); a "vnoiseS:" prefix
adds Gaussian noise of S m/s to each component of each track's velocity at each decision (the
tracker's own velocities untouched): how exact a perceiver of the motion has to be; a
"vbiasS:" prefix adds such noise drawn once per track and kept (an error that persists, as a
network's may).
(The log's figures for headings of a track seen once, "f8" / "s1.5", came from a
package change tried and reverted.)
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from qnav.contracts.lookahead import shielded_actions
from qnav.contracts.motion import Outcome, move_obstacles
from qnav.controller.lookahead import LookaheadSettings, risks_of
from qnav.controller.perception import TrackerSettings
from qnav.lab.oracle import collision_shares
from qnav.sim.evaluate import EvalResult, EvalSettings, episode_outcomes
from qnav.sim.geometry import cast_lidar
from qnav.sim.world import observe, take_rows
from qnav.tracking import LookaheadAgent, noisy
from qnav.training.agent import policy_agent
from qnav.training.run_folder import load_network


def ruled(q_values, shares, chosen, rule):  # type: ignore[no-untyped-def]
    if rule == "shield":  # the rule before lookahead.overrule_share: overrule wherever safer
        return shielded_actions(q_values, shares, 0.0)
    if rule.startswith("near"):  # the committed rule since, at this overrule share
        return shielded_actions(q_values, shares, float(rule[4:]))
    assert rule.startswith("tol"), rule  # the former lookahead.tolerance
    allowed = shares <= shares.min(axis=1, keepdims=True) + float(rule[3:])
    return np.where(allowed, q_values, -np.inf).argmax(axis=1)


class RuledShield(LookaheadAgent):
    rule = "shield"
    truth = False
    first_known = False
    rest_periods = 0
    still = False
    smear_s = 0.0
    smear_parts = ("ego", "obs")
    deskew = False
    learned = None
    velocity_noise_mps = 0.0
    persistent_noise = False
    window = None
    previous_pose = None
    state = None
    counting = np.zeros(0, dtype=bool)

    def watch(self, state, counting):  # type: ignore[no-untyped-def]
        self.state, self.counting = state, counting.copy()

    def act(self, observation):  # type: ignore[no-untyped-def]
        chosen = self.inner.act(observation)
        scan_m = self.smeared(observation) if self.smear_s else observation.scan_m
        scans = noisy(scan_m, self.range_noise_m, self._noise)
        times_s = self.steps * self.world.control_period_s
        if self.rest_periods:
            for row in np.flatnonzero(self.steps == 0):
                self.stand(row)
        for row, car in enumerate(self.cars):
            now_s = float(times_s[row])
            if self.deskew:  # the scan's first beam left smear_s before the decision
                delays_s = self.smear_s / scans.shape[1] * np.arange(scans.shape[1])
                car.observe(
                    now_s, observation.pose[row], now_s - self.smear_s, scans[row], delays_s
                )
            else:
                car.observe(now_s, observation.pose[row], now_s, scans[row])
        if self.first_known:  # the first decision's tracks get the true velocities
            for row in np.flatnonzero(self.steps == 0):
                for track in self.cars[row].tracker._tracks:
                    gaps = np.linalg.norm(self.state.obstacle_xy[row] - track.centres[-1], axis=1)
                    track.velocity = self.state.obstacle_velocity[row, gaps.argmin()].copy()
        if self.truth:
            counted = np.flatnonzero(self.counting)
            shares = np.zeros((len(chosen), 3))
            shares[counted] = collision_shares(self.world, take_rows(self.state, counted))
        elif self.still or self.learned is not None or self.velocity_noise_mps:
            kept = [(t, t.velocity) for car in self.cars for t in car.tracker._tracks]
            learned = self.read_motion(scans, observation.pose)
            for row, car in enumerate(self.cars):
                for track in car.tracker._tracks:
                    if self.velocity_noise_mps:
                        error = self._noise.normal(0.0, self.velocity_noise_mps, 2)
                        if self.persistent_noise:  # the track's first draw, kept on it
                            if not hasattr(track, "gauge_error"):
                                track.gauge_error = error
                            error = track.gauge_error
                        track.velocity = track.velocity + error
                    else:  # positions; no or learned velocities
                        track.velocity = learned(row, track.centres[-1])
            shares = risks_of(self.cars, list(observation.target_xy))
            for track, velocity in kept:
                track.velocity = velocity
        else:
            shares = risks_of(self.cars, list(observation.target_xy))
        action = ruled(self.inner.last_q, shares, chosen, self.rule)
        self.overruled += int(np.sum(action != chosen))
        self.decisions += action.size
        self.steps += 1
        return action

    def read_motion(self, scans, poses):  # type: ignore[no-untyped-def]
        """A function (row, centre) -> the velocity the learned perceiver gives an obstacle
        there (zero without a perceiver: `still`)."""
        if self.learned is None:
            return lambda row, centre: np.zeros(2)
        from learned_motion import WINDOW, reproject
        from learned_motion_grid import per_beam
        from learned_motion_points import (
            AttentivePointMotionNetwork,
            PointMotionNetwork,
            points,
            raw,
            track_velocity,
        )

        if self.window is None:
            self.window = (
                np.repeat(scans[:, None], WINDOW, 1),
                np.repeat(poses[:, None], WINDOW, 1),
            )
        past_scans, past_poses = self.window
        past_scans = np.concatenate([past_scans[:, 1:], scans[:, None]], axis=1)
        past_poses = np.concatenate([past_poses[:, 1:], poses[:, None]], axis=1)
        fresh = self.steps == 0
        past_scans[fresh] = scans[fresh, None]
        past_poses[fresh] = poses[fresh, None]
        self.window = (past_scans, past_poses)
        angles = self.world.lidar.beam_angles_rad()
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        heading = poses[:, 2:3] + angles[None]
        seen = np.isfinite(scans) & (scans < 10.0)
        r = np.where(seen, scans, 0.0)
        hits = np.stack(
            [poses[:, 0:1] + r * np.cos(heading), poses[:, 1:2] + r * np.sin(heading)], axis=-1
        )
        reach_m = self.world.obstacles.radius_m + 0.15
        if isinstance(self.learned, PointMotionNetwork | AttentivePointMotionNetwork):
            # per track, from its returns' points
            cloud = points(raw(past_scans, past_poses, angles), self.world)
            ok = cloud[1]

            def from_points(row, centre):  # type: ignore[no-untyped-def]
                on = ok[row, -1] & (np.linalg.norm(hits[row] - centre, axis=1) < reach_m)
                if not on.any():
                    return np.zeros(2)
                forward, left = track_velocity(self.learned, cloud, row, np.flatnonzero(on))
                return np.array(
                    [c[row, 0] * forward - s[row, 0] * left, s[row, 0] * forward + c[row, 0] * left]
                )

            return from_points
        aligned = reproject(past_scans, past_poses, angles)
        with torch.no_grad():
            robot = per_beam(self.learned, torch.from_numpy(aligned)).numpy().astype(np.float64)
        vx = c * robot[..., 0] - s * robot[..., 1]
        vy = s * robot[..., 0] + c * robot[..., 1]

        def velocity(row, centre):  # type: ignore[no-untyped-def]
            on = seen[row] & (np.linalg.norm(hits[row] - centre, axis=1) < reach_m)
            if not on.any():
                return np.zeros(2)
            return np.array([vx[row][on].mean(), vy[row][on].mean()])

        return velocity

    def smeared(self, observation):  # type: ignore[no-untyped-def]
        """The scans a rotating lidar would give, its turn of `smear_s` ending now."""
        world, state, slices = self.world, self.state, 40
        now = state.pose
        previous = now if self.previous_pose is None else self.previous_pose
        previous = np.where((self.steps == 0)[:, None], now, previous)
        turned = np.angle(np.exp(1j * (now[:, 2] - previous[:, 2])))
        scans = np.empty_like(observation.scan_m)
        beams = world.lidar.num_beams
        for k in range(slices):
            back_s = self.smear_s * (1 - (k + 0.5) / slices)
            share = back_s / world.control_period_s * ("ego" in self.smear_parts)
            pose = now.copy()
            pose[:, :2] -= share * (now[:, :2] - previous[:, :2])
            pose[:, 2] -= share * turned
            xy, _ = move_obstacles(
                state.obstacle_xy,
                -state.obstacle_velocity,
                world.obstacles.radius_m,
                world.arena.size_m,
                back_s * ("obs" in self.smear_parts),
            )
            part = slice(k * beams // slices, (k + 1) * beams // slices)
            cast = cast_lidar(pose, world.lidar, world.arena, xy, world.obstacles.radius_m)
            scans[:, part] = cast[:, part]
        self.previous_pose = now.copy()
        return scans

    def stand(self, row):  # type: ignore[no-untyped-def]
        """`rest_periods` scans from the start pose before the episode, the obstacles where they
        were then."""
        world, period = self.world, self.world.control_period_s
        state = take_rows(self.state, np.array([row]))
        xy, velocity = state.obstacle_xy, state.obstacle_velocity
        before = []
        for _ in range(self.rest_periods):
            xy, velocity = move_obstacles(
                xy, -velocity, world.obstacles.radius_m, world.arena.size_m, period
            )
            velocity = -velocity
            before.append(observe(world, state._replace(obstacle_xy=xy)).scan_m[0])
        for k, clean in enumerate(reversed(before)):
            time_s = (k - self.rest_periods) * period
            scan = noisy(clean[None], self.range_noise_m, self._noise)[0]
            self.cars[row].observe(time_s, state.pose[0], time_s, scan)


def shielded(  # type: ignore[no-untyped-def]
    run: Path, episodes: int, seed: int, lookahead: LookaheadSettings, kind=None
):
    """(agent, world, settings): `run`'s greedy DQN shielded by the controller's look ahead as
    `kind` (RuledShield by default), over `episodes` layouts of `seed`."""
    network, folder = load_network(run)
    settings = EvalSettings(episodes=episodes, seed=seed)
    worlds = min(settings.num_worlds, episodes)
    policy = policy_agent(
        network, folder.world, worlds, folder.train.window, hold_steps=1, seed=seed
    )
    agent = (kind or RuledShield)(
        policy, folder.world, worlds, tracker=TrackerSettings(), lookahead=lookahead, seed=seed
    )
    return agent, folder.world, settings


def main() -> None:
    torch.set_num_threads(1)
    run, episodes, seed = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    for named in sys.argv[4].split(","):
        started = time.time()
        *prefixes, rule = named.split(":")
        default_s = LookaheadSettings().shield_horizon_s
        horizon_s = next((float(p[1:]) for p in prefixes if p.startswith("h")), default_s)
        lookahead = LookaheadSettings(mode="shield", shield_horizon_s=horizon_s)
        agent, world, settings = shielded(run, episodes, seed, lookahead)
        agent.first_known = "v0" in prefixes
        agent.rest_periods = next((int(p[4:]) for p in prefixes if p.startswith("rest")), 0)
        agent.truth = "truth" in prefixes
        agent.still = "still" in prefixes
        noise = next((p[6:] for p in prefixes if p.startswith(("vnoise", "vbias"))), "0")
        agent.velocity_noise_mps = float(noise)
        agent.persistent_noise = any(p.startswith("vbias") for p in prefixes)
        learned = next((p[8:] for p in prefixes if p.startswith("learned@")), None)
        if learned is not None:
            import learned_motion_grid
            import learned_motion_points

            grid = "subcell" in torch.load(learned)
            agent.learned = (learned_motion_grid if grid else learned_motion_points).load(learned)
        agent.deskew = "deskew" in prefixes
        agent.smear_parts = tuple(p for p in ("ego", "obs") if p in prefixes) or ("ego", "obs")
        agent.smear_s = next((float(p[5:]) for p in prefixes if p.startswith("smear")), 0.0)
        agent.rule = rule
        label = ":".join(
            [
                f"h{horizon_s:g}",
                *sorted(
                    p
                    for p in prefixes
                    if p in ("v0", "truth", "still", "ego", "obs", "deskew")
                    or p.startswith(("rest", "smear", "learned", "vnoise", "vbias"))
                ),
                rule,
            ]
        )
        outcomes, steps = episode_outcomes(world, agent, settings, watch=agent.watch)
        result = EvalResult.of_outcomes(outcomes, steps)
        collided = steps[outcomes == Outcome.COLLISION]
        print(
            json.dumps(
                {
                    "run": str(run),
                    "rule": label,
                    "seed": seed,
                    "episodes": episodes,
                    "success": result.success,
                    "collision": result.collision,
                    "overruled": agent.overruled_share,
                    "collisions_by_step_5_10_20": [int((collided <= k).sum()) for k in (5, 10, 20)],
                    "minutes": round((time.time() - started) / 60, 1),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
