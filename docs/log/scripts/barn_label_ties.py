"""Gauge: are the learner's disagreements with the planner near-ties? For each state along the
planner's own paths in 128 validation caves: the planner's heading error against its forward
threshold (margin = | |error| - aligned |), and whether the network's greedy action differs.

    .venv/bin/python docs/log/scripts/barn_label_ties.py RUN WEIGHTS.pt
(needs the validation set barn_offline_bc.py caches in /tmp/g/valset)
"""
import math, sys
from dataclasses import replace
from pathlib import Path
import numpy as np, torch
from qnav.sim.mapplan import MapPlanner
from qnav.sim.world import reset
from qnav.training.episode_log import read_rounds
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import load_network
torch.set_num_threads(1)
run, w = Path(sys.argv[1]), Path(sys.argv[2])
net, s = load_network(run, w)
world = replace(s.world, layout=replace(s.world.layout, split="validation", worlds=128, order="cycle"))
eps = read_rounds(Path("/tmp/g/valset"))[1]
state = reset(world, np.zeros(128, dtype=np.int64), np.arange(128, dtype=np.int64))
planner = MapPlanner(world)
d = EpisodeReplay(world, sum(len(e.action) + 1 for e in eps) + 10, s.train.window)
layout_of = []
for i, e in enumerate(eps):
    d.add(e); layout_of += [int(state.layout[i])] * len(e.action)
now = d.transitions(); layout_of = np.array(layout_of)
with torch.no_grad():
    pred = torch.cat([net(torch.from_numpy(d.windows(c))) for c in np.array_split(now, 40)]).argmax(1).numpy()
label = d.action[now]
margins = np.empty(now.size)
st = planner.settings
for k, (i, lay) in enumerate(zip(now, layout_of)):
    pose = d.pose[i]
    grid = planner.grid(int(lay))
    costs = grid.at(pose[:2] + st.lookahead_m * planner._offsets)
    b = int(np.argmin(costs))
    wanted = math.atan2(planner._offsets[b, 1], planner._offsets[b, 0])
    err = (wanted - pose[2] + math.pi) % (2 * math.pi) - math.pi
    centres = planner.layouts.cylinders_of(np.array([lay]))[0]
    gap = np.sqrt(((centres - pose[:2]) ** 2).sum(-1)).min() - planner.layouts.cylinder_radius_m - world.robot_radius_m
    aligned = st.open_aligned_rad if gap > st.open_m else st.aligned_rad
    margins[k] = abs(abs(err) - aligned)
differ = pred != label
print(f"{w}: {now.size} states, disagree {differ.mean():.3f}")
for lo, hi in ((0, 0.05), (0.05, 0.1), (0.1, 0.2), (0.2, 0.5), (0.5, 10)):
    m = (margins >= lo) & (margins < hi)
    print(f"  margin {lo:.2f}-{hi:.2f} rad: share of states {m.mean():.3f}, disagree {differ[m].mean():.3f}, share of all disagreements {(differ & m).sum() / differ.sum():.3f}")
# turn-vs-turn (left vs right) disagreements
lr = differ & (pred != 0) & (label != 0)
print(f"  left/right swapped: {lr.sum() / differ.sum():.3f} of disagreements")
