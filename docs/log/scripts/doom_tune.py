# Ad hoc measurement of issue 19 (2026-12-06); runs against commit the log names (training.sampling.doom_bounds exists there only).
"""Minutes-scale gauge: fine-tune a run's network on its own replay (fresh obstacles) for some
iterations, with or without the search's bounds, and measure on held-out batches how often its Q
ranks a safe action first where a search finds some action doomed and another not."""
import sys, time
from dataclasses import replace
import numpy as np
from pathlib import Path
from qnav.training.algorithm import DoubleDQN
from qnav.training.agent import q_values
from qnav.training.episode_log import read_rounds
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import load_network
from qnav.training.sampling import DOOM_ROWS, sample
import torch
torch.set_num_threads(1)
run = Path(sys.argv[1]); weight = float(sys.argv[2]); iterations = int(sys.argv[3])
network, settings = load_network(run)
config, train = settings.world, replace(settings.train, doom_bound_weight=weight, threads=1)
eps = [e for r in read_rounds(run / "episodes") for e in r][-300:]
replay = EpisodeReplay(config, sum(e.pose.shape[0] for e in eps) + 10, train.window, obstacle_inputs=train.obstacle_inputs)
for e in eps: replay.add(e)
held = [sample(replay, 256, np.random.default_rng(100 + i), "paper", n_step=5, gamma=train.gamma,
               obstacle_redraw_probability=1.0, doom_rows=256) for i in range(25)]
def measure(net):
    ranks, safe_q, all_q, ord_q = [], [], [], []
    for b in held:
        d = b.doom.doomed; q = q_values(net, b.frames[:, : train.window])
        dec = d.any(1) & ~d.all(1)
        for r in np.flatnonzero(dec):
            ranks.append(q[r][~d[r]].max() > q[r][d[r]].max()); safe_q.append(q[r][~d[r]].max())
        all_q += list(q[d.all(1)].max(1)); ord_q += list(q[~d.any(1)].max(1))
    return f"safe first {np.mean(ranks):.3f} (n={len(ranks)}) best Q: decisive {np.median(safe_q):.2f} all-doomed {np.median(all_q):.2f} ordinary {np.median(ord_q):.2f}"
print("before", measure(network), flush=True)
dqn = DoubleDQN(network, train)
rng = np.random.default_rng(0); t = time.time()
for i in range(1, iterations + 1):
    b = sample(replay, train.batch_size, rng, train.relabel, n_step=train.n_step, gamma=train.gamma,
               obstacle_redraw_probability=1.0, doom_rows=DOOM_ROWS if weight > 0 else 0)
    dqn.update(b, i)
    if i % (iterations // 4) == 0:
        dqn.online.eval(); print(i, f"{time.time()-t:.0f}s", measure(dqn.online), flush=True); dqn.online.train()
