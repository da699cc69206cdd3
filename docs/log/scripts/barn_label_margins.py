"""The planner's margin at every stored state of DAgger rounds: | |heading error| - forward
threshold | in rad (how near its label was to flipping), in the rounds' order.

    .venv/bin/python docs/log/scripts/barn_label_margins.py RUN [RUN...]
writes /tmp/g/margins-RUN.npy for each, read by barn_offline_bc.py tie=RAD.
"""
import math, sys
from pathlib import Path
import numpy as np
from qnav.sim.mapplan import MapPlanner
from qnav.sim.world import reset
from qnav.training.episode_log import read_rounds
from qnav.training.run_folder import read_settings

def pose_margins(planner, world, pose, lay):
    """| |heading error| - forward threshold | (rad) of the planner at poses (N, 3) in layout `lay`."""
    st = planner.settings
    grid = planner.grid(int(lay))
    pts = pose[:, None, :2] + st.lookahead_m * planner._offsets[None]
    costs = grid.at(pts.reshape(-1, 2)).reshape(pose.shape[0], -1)
    b = np.argmin(costs, axis=1)
    wanted = np.arctan2(planner._offsets[b, 1], planner._offsets[b, 0])
    err = (wanted - pose[:, 2] + math.pi) % (2 * math.pi) - math.pi
    centres = planner.layouts.cylinders_of(np.array([lay]))[0]
    gap = np.sqrt(((centres[None] - pose[:, None, :2]) ** 2).sum(-1)).min(1) - planner.layouts.cylinder_radius_m - world.robot_radius_m
    aligned = np.where(gap > st.open_m, st.open_aligned_rad, st.aligned_rad)
    return np.abs(np.abs(err) - aligned)

def episode_margins(planner, world, e, lay):
    return pose_margins(planner, world, e.pose[:-1], lay)

if __name__ == "__main__":
    out = {}
    for r in sys.argv[1:]:
        run = Path(r); s = read_settings(run); world = s.world
        planner = MapPlanner(world)
        rounds = read_rounds(run / "imitation")
        ms = []
        for k, eps in enumerate(rounds):
            n = len(eps)
            ids = np.arange(k * n, (k + 1) * n, dtype=np.int64)
            state = reset(world, np.full(n, 2_000_011 + s.train.seed, dtype=np.int64), ids)
            for e, lay in zip(eps, state.layout):
                ms.append(episode_margins(planner, world, e, lay))
        np.save(f"/tmp/g/margins-{run.name}.npy", np.concatenate(ms))
        print(run, len(ms), flush=True)
