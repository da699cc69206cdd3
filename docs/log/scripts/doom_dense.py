# Ad hoc measurement of issue 19 (2026-12-06); runs against commit 97b3cd2 (training.sampling.doom_bounds).
"""Can the Q-network rank a safe action above a doomed one when the search's verdicts are dense?
Collect the decisive steps of many batches of a run's own replay (fresh obstacles, every step
searched), then fit the network on those alone with the two search terms (doomed actions at or
under their bound; surviving actions at or over their floor, computed once with the starting
network), and measure the ranking on held-out decisive steps after each epoch."""
import sys, time
from pathlib import Path
import numpy as np
import torch
from qnav.training.agent import q_values
from qnav.training.algorithm import survivor_floor
from qnav.training.episode_log import read_rounds
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import load_network
from qnav.training.sampling import sample

torch.set_num_threads(1)
run, batches, epochs = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
network, settings = load_network(run)
config, train = settings.world, settings.train
eps = [e for r in read_rounds(run / "episodes") for e in r][-300:]
replay = EpisodeReplay(config, sum(e.pose.shape[0] for e in eps) + 10, train.window,
                       obstacle_inputs=train.obstacle_inputs)
for e in eps:
    replay.add(e)
rng = np.random.default_rng(0)
frames, doomed, bound, floor_rows = [], [], [], []
t = time.time()
for i in range(batches):
    b = sample(replay, 256, rng, "paper", n_step=5, gamma=train.gamma,
               obstacle_redraw_probability=1.0, doom_rows=256)
    d = b.doom.doomed
    dec = np.flatnonzero(d.any(1) & ~d.all(1))
    with torch.no_grad():
        floor = survivor_floor(network, network, b.doom, torch.device("cpu")).numpy()
    full = np.full((256, 3), np.nan, dtype=np.float32)
    full[b.doom.survivor_index[:, 0], b.doom.survivor_index[:, 1]] = floor
    frames.append(b.frames[dec, : train.window]); doomed.append(d[dec]); bound.append(b.doom.bound[dec])
    floor_rows.append(full[dec])
frames, doomed, bound, floors = map(np.concatenate, (frames, doomed, bound, floor_rows))
n = len(frames); split = int(0.75 * n)
print(f"{n} decisive steps from {batches} batches in {time.time() - t:.0f} s", flush=True)

def ranking(rows):
    q = q_values(network, frames[rows])
    d = doomed[rows]
    return np.mean([q[r][~d[r]].max() > q[r][d[r]].max() for r in range(len(rows))])

train_rows, held = np.arange(split), np.arange(split, n)
print("epoch 0: train", round(ranking(train_rows), 3), "held-out", round(ranking(held), 3), flush=True)
optimizer = torch.optim.Adam(network.parameters(), lr=train.learning_rate)
for epoch in range(1, epochs + 1):
    network.train()
    for chunk in np.array_split(rng.permutation(train_rows), max(1, split // 64)):
        q = network(torch.from_numpy(frames[chunk])).float()
        d = torch.from_numpy(doomed[chunk]); lo = torch.from_numpy(floors[chunk])
        over = torch.relu(q - torch.from_numpy(bound[chunk]))[d]
        under = torch.relu(lo - q)[~d & ~torch.isnan(lo)]
        loss = (over**2).mean() + (under**2).mean()
        optimizer.zero_grad(); loss.backward(); optimizer.step()
    network.eval()
    print(f"epoch {epoch}: train", round(ranking(train_rows), 3), "held-out", round(ranking(held), 3), flush=True)
