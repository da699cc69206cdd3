# Ad hoc measurement of issue 19 (2026-12-06, session 26).
"""The bar for a learned motion perceiver, in its own units: the onboard tracker's velocity
error on the same held-out windows (2,000 windows of other layouts, five scans each), by the
same anatomy as `learned_motion_points.py --anatomy`.

Until now the bar was read off a curve (the shield's success against noise added to the
tracker's velocities, kept per track: session 23); this measures the tracker itself. A fresh
tracker (the controller's `ObstacleTracker`, the scenario's obstacle radius) takes the window's
five scans in order; each obstacle (its returns in the newest scan) is paired with the track
whose centre is nearest their mean, within the radius + 0.3 m; an obstacle with no such track
counts as unmatched (its error: the true speed, as a forecast without it would err; the
share matched is printed first).

Usage: tracker_motion_error.py SCENARIO [RANGE_NOISE_M]
(RANGE_NOISE_M: Gaussian noise added to every range the tracker reads, as `qnav.tracking.noisy`)
"""

from __future__ import annotations

import sys

import numpy as np
from learned_motion import collect
from learned_motion_points import print_anatomy, raw

from qnav.controller.perception import ObstacleTracker, TrackerSettings, box_walls
from qnav.sim.config import scenario
from qnav.tracking import noisy


def main() -> None:
    world = scenario(sys.argv[1])
    sigma_m = float(sys.argv[2]) if len(sys.argv) > 2 else 0.0
    random = np.random.default_rng(0)
    hx, hy, hidx, turned = collect(world, 2000, seed=1005, with_turns=True, window_of=raw)
    angles = world.lidar.beam_angles_rad()
    settings = TrackerSettings(obstacle_radius_m=world.obstacles.radius_m)
    walls = box_walls(world.arena.size_m)
    beams_n = hx.shape[2] - 3
    errors, bounced, range_m, returns, matched = [], [], [], [], []
    for w in range(len(hx)):
        tracker = ObstacleTracker(settings, walls, angles)
        for k in range(hx.shape[1]):
            scan, pose = (
                hx[w, k, :beams_n].astype(np.float64),
                hx[w, k, beams_n:].astype(np.float64),
            )
            scan = noisy(scan, sigma_m, random).astype(np.float64)
            tracks = tracker.update(k * world.control_period_s, scan, pose)
        pose = hx[w, -1, beams_n:].astype(np.float64)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        for m in np.unique(hidx[w][hidx[w] >= 0]):
            on = hidx[w] == m
            r = hx[w, -1, :beams_n][on].astype(np.float64)
            heading = pose[2] + angles[on]
            seen = np.array([pose[0] + r * np.cos(heading), pose[1] + r * np.sin(heading)]).T
            truth = hy[w][np.flatnonzero(on)[0]].astype(np.float64)
            gap = np.linalg.norm(tracks.xy_m - seen.mean(0), axis=1) if len(tracks.xy_m) else []
            found = len(gap) > 0 and gap.min() < world.obstacles.radius_m + 0.3
            if found:
                vx, vy = tracks.velocity_mps[int(np.argmin(gap))]
                robot = np.array([c * vx + s * vy, -s * vx + c * vy])
                errors.append(float(np.linalg.norm(robot - truth)))
            else:
                errors.append(float(np.linalg.norm(truth)))
            matched.append(found)
            bounced.append(bool(turned[w, m]))
            range_m.append(float(np.median(r)))
            returns.append(int(on.sum()))
    error, bounced_a, range_a = np.array(errors), np.array(bounced), np.array(range_m)
    returns_a, matched_a = np.array(returns), np.array(matched)
    print(
        f"{len(error)} obstacles, {matched_a.mean():.3f} matched to a track: median "
        f"{np.median(error):.4f} p90 {np.quantile(error, 0.9):.4f}"
    )
    print_anatomy(error, bounced_a, range_a, returns_a, digits=4)


if __name__ == "__main__":
    main()
