"""Gauge: the always-forward driver under the proximity stop in the realistic room, with the
stop the simulator lacks (the robot's velocity lag towards zero, where the field forbids every
action) and, with `grow`, a turn forbidden while the car would coast into a reading within the
footprint plus its coasting distance (forward speed x the linear time constant) ahead.

    .venv/bin/python docs/log/scripts/proximity_coasting.py none|grow EPISODES
"""
import sys
from dataclasses import replace
import numpy as np
from qnav.contracts.motion import Outcome, action_velocities, step_velocity_lag
from qnav.controller.proximity import allowed_actions, blocked_parts, field_ranges, guarded_action
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings
from qnav.sim.room import room_clearance
from qnav.sim.world import observe, reset, scatter, step, step_outcome
from qnav.tracking import fitted_proximity
grow = sys.argv[1] == "grow"; episodes = int(sys.argv[2])
world = scenario('realistic-room'); settings = EvalSettings(episodes=episodes, seed=12345)
prox = fitted_proximity(world)
world = replace(world, max_episode_steps=settings.max_episode_steps)
tau = world.dynamics.linear_time_constant_s
angles = world.lidar.beam_angles_rad()
linear = np.array([v for v, _ in action_velocities(world.dynamics, world.control_period_s)])
values = np.array([1.0, 0.5, 0.0])
W = 64; episode = np.arange(W); seed = np.full(W, settings.seed)
state = reset(world, seed, episode); obs = observe(world, state)
active = np.ones(W, bool); nxt = W; counts = dict(success=0, static=0, moving=0, unfinished=0, stops=0)
while active.any():
    action = np.zeros(W, np.int64); stop = np.zeros(W, bool)
    for r in range(W):
        ranges = field_ranges(obs.scan_m[r], 0.0, np.inf, False)
        b = blocked_parts(angles, ranges, prox.footprint_m, prox.travel_m)
        allowed = allowed_actions(linear, b)
        if grow and allowed[1:].any():
            coast = max(float(state.velocity[r, 0]), 0.0) * tau
            ok = np.isfinite(ranges)
            x = ranges[ok] * np.cos(angles[ok])
            if ((ranges[ok] < prox.footprint_m + coast) & (x > 0)).any():
                allowed = allowed & (linear != 0)  # no turn while coasting into something
        choice = guarded_action(0, allowed, values)
        stop[r] = choice is None
        action[r] = 1 if choice is None else choice
    counts["stops"] += int((stop & active).sum())
    before = state
    state, obs, tr = step(world, state, action)
    if stop.any():
        idx = np.flatnonzero(stop)
        pose, vel = step_velocity_lag(before.pose[idx], before.velocity[idx], np.zeros(idx.size), np.zeros(idx.size), params=world.dynamics, period_s=world.control_period_s)
        p2, v2 = state.pose.copy(), state.velocity.copy(); p2[idx] = pose; v2[idx] = vel
        state = state._replace(pose=p2, velocity=v2)
        obs = observe(world, state)
        dist = np.linalg.norm(state.target_xy - state.pose[:, :2], axis=1)
        out = step_outcome(world, dist, obs.clearance_m)
        term = out != Outcome.RUNNING
        tr = tr._replace(outcome=out, terminated=term, truncated=~term & (state.steps >= world.max_episode_steps))
    done = (tr.terminated | tr.truncated) & active
    static, _ = room_clearance(world, state)
    for e in np.flatnonzero(done).tolist():
        o = int(tr.outcome[e])
        if o == Outcome.COLLISION:
            counts["static" if static[e] < world.robot_radius_m else "moving"] += 1
        else:
            counts["success" if o == Outcome.SUCCESS else "unfinished"] += 1
    idx = np.flatnonzero(done); c = min(idx.size, settings.episodes - nxt)
    active[idx[c:]] = False; idx = idx[:c]
    if c:
        episode[idx] = np.arange(nxt, nxt + c); nxt += c
        fresh = reset(world, seed[idx], episode[idx]); state = scatter(state, idx, fresh); obs = scatter(obs, idx, observe(world, fresh))
print(sys.argv[1:], counts)
