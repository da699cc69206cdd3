"""Offline gauge: behaviour cloning on stored DAgger rounds, judged by agreement / cross-entropy
against the planner on a fixed validation set: the planner's labels along the shipped seed-0
network's paths and along the planner's own, 128 validation caves (cached in /tmp/g/valset).

    .venv/bin/python docs/log/scripts/barn_offline_bc.py data=RUN[,RUN...] iters=8000 save=FILE.pt
    (options: range=M (ranges encoded at this scale, clipped), window=K, mirror=P (windows reflected left-right with chance P), tie=RAD (near-tie weights; margins from barn_label_margins.py), lr=,
    batch=, rounds=)
Export a saved network with a run's settings.toml (its window set to K) beside it as model.pt:
    qnav export DIR -o FILE.onnx --weights int8 --eval-episodes 0 --turn-commitment
"""
from __future__ import annotations
import sys, time
from dataclasses import replace
from pathlib import Path
import numpy as np
import torch
from torch.nn import functional
from qnav.sim.mapplan import MapPlanner
from qnav.training.agent import policy_agent
from qnav.training.collect import collect_round
from qnav.training.episode_log import read_rounds, write_round
from qnav.training.networks import make_network
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import load_network, read_settings

torch.set_num_threads(1)
args = dict(a.split("=", 1) for a in sys.argv[1:])
runs = [Path(r) for r in args.get("data", "runs/cave/dagger-recurrent-seed0").split(",")]
iters = int(args.get("iters", 8000))
rounds_max = int(args.get("rounds", 10)); lr = float(args.get("lr", 5e-4)); batch = int(args.get("batch", 256))
settings = read_settings(runs[0])
world, train = settings.world, settings.train
if "range" in args:  # the scale of the network's ranges (and its target distance): nearer, finer
    world = replace(world, lidar=replace(world.lidar, max_range_m=float(args["range"])))
window = int(args.get("window", train.window))

def replay_of(episodes, w):
    data = EpisodeReplay(w, sum(len(e.action) + 1 for e in episodes) + 10, window)
    for e in episodes:
        data.add(e)
    return data

val_dir = Path("/tmp/g/valset")
val_world = replace(world, layout=replace(world.layout, split="validation", worlds=128, order="cycle"))
if not val_dir.exists():
    net, _ = load_network(Path("runs/cave/dagger-recurrent-seed0"), Path("runs/cave/dagger-recurrent-seed0/best.pt"))
    expert = MapPlanner(val_world)
    eps = collect_round(val_world, policy_agent(net, val_world, 128, train.window), 0, np.arange(128, dtype=np.int64),
                        labeller=lambda s: expert.act_at(s.pose, s.layout))
    write_round(val_dir, 0, eps)
    eps2 = collect_round(val_world, expert, 0, np.arange(128, dtype=np.int64), labeller=lambda s: expert.act_at(s.pose, s.layout))
    write_round(val_dir, 1, eps2)
vr = read_rounds(val_dir)
val_own, val_expert = replay_of(vr[0], val_world), replay_of(vr[1], val_world)

episodes = [e for r in runs for rnd in read_rounds(r / "imitation")[:rounds_max] for e in rnd]
data = replay_of(episodes, world)
stored = data.transitions()
tie = float(args.get("tie", 0))
mirror = float(args.get("mirror", 0))
weight_of = np.ones(data.size)
if tie:
    margins = np.concatenate([np.load(f"/tmp/g/margins-{r.name}.npy") for r in runs])
    assert margins.size == stored.size, (margins.size, stored.size)
    weight_of[stored] = np.clip(margins / tie, 0.1, 1.0)
    print(f"tie weights: mean {weight_of[stored].mean():.3f}", flush=True)
print(f"data: {len(episodes)} episodes, {stored.size} windows", flush=True)

torch.manual_seed(0)
network = make_network(world, train)
opt = torch.optim.Adam(network.parameters(), lr=lr)
def score(d, n=12000):
    rng = np.random.default_rng(1)
    now = d.transitions()
    now = rng.choice(now, min(n, now.size), replace=False)
    network.eval()
    with torch.no_grad():
        logits = torch.cat([network(torch.from_numpy(d.windows(c))) for c in np.array_split(now, 8)])
    network.train()
    lab = torch.from_numpy(d.action[now])
    return float((logits.argmax(1) == lab).float().mean()), float(functional.cross_entropy(logits, lab))

rng = np.random.default_rng(0)
t = time.perf_counter()
for it in range(1, iters + 1):
    now = stored[rng.integers(0, stored.size, batch)]
    frames = data.windows(now); labels = data.action[now]
    if mirror:  # the worlds have no handedness: reflect a share of the windows left-right
        flip = rng.random(batch) < mirror
        beams = data.num_beams
        frames = frames.copy(); labels = labels.copy()
        frames[flip, :, :beams] = frames[flip][:, :, (-np.arange(beams)) % beams]
        frames[flip, :, beams + 1] *= -1  # the target's sin(bearing)
        labels[flip] = np.array([0, 2, 1])[labels[flip]]
    logits = network(torch.from_numpy(frames))
    weights = torch.from_numpy(weight_of[now].astype(np.float32))
    loss = (functional.cross_entropy(logits, torch.from_numpy(labels), reduction="none") * weights).sum() / weights.sum()
    opt.zero_grad(); loss.backward()
    torch.nn.utils.clip_grad_norm_(network.parameters(), 10.0); opt.step()
    if it % 2000 == 0 or it == iters:
        tr = score(data); vo = score(val_own); ve = score(val_expert)
        print(f"{' '.join(sys.argv[1:])} it={it} {time.perf_counter()-t:.0f}s train acc={tr[0]:.3f} ce={tr[1]:.3f} | val own acc={vo[0]:.3f} ce={vo[1]:.3f} | val planner-path acc={ve[0]:.3f} ce={ve[1]:.3f}", flush=True)
out = args.get("save")
if out:
    torch.save({"online": network.state_dict()}, out)
