# Ad hoc measurement of issue 19 (2026-12-06); runs against commit the log names (training.sampling.doom_bounds exists there only).
"""On a run's own replay with fresh obstacles: does its Q rank safe above doomed where a search says
some action is doomed and another not, and how far above their bound are doomed actions' values?"""
import sys
import numpy as np
from pathlib import Path
from qnav.training.episode_log import read_rounds
from qnav.training.replay import EpisodeReplay
from qnav.training.run_folder import load_network
from qnav.training.sampling import sample
from qnav.training.agent import q_values
run = Path(sys.argv[1])
network, settings = load_network(run, Path(sys.argv[2]) if len(sys.argv) > 2 else None)
config, train = settings.world, settings.train
eps = [e for r in read_rounds(run / "episodes") for e in r]
eps = eps[-300:]
replay = EpisodeReplay(config, sum(e.pose.shape[0] for e in eps) + 10, train.window, obstacle_inputs=train.obstacle_inputs)
for e in eps: replay.add(e)
rng = np.random.default_rng(0)
ranks, excess_dec, excess_all, gap, qsafe_dec, qall = [], [], [], [], [], []
for i in range(40):
    b = sample(replay, 256, rng, "paper", n_step=5, gamma=train.gamma, obstacle_redraw_probability=1.0, doom_rows=256)
    d = b.doom.doomed
    q = q_values(network, b.frames[:, : train.window])
    dec = d.any(1) & ~d.all(1)
    alld = d.all(1)
    for r in np.flatnonzero(dec):
        best_safe = q[r][~d[r]].max(); best_doom = q[r][d[r]].max()
        ranks.append(best_safe > best_doom); gap.append(best_safe - best_doom)
        excess_dec.append(np.maximum(0, q[r][d[r]] - b.doom.bound[r][d[r]]).mean())
        qsafe_dec.append(best_safe)
    for r in np.flatnonzero(alld):
        excess_all.append(np.maximum(0, q[r] - b.doom.bound[r]).mean()); qall.append(q[r].max())
print(run, "decisive", len(ranks), "safe ranked first", np.mean(ranks).round(3), "median gap", np.median(gap).round(3),
      "doomed excess on decisive", np.mean(excess_dec).round(3), "best safe Q", np.median(qsafe_dec).round(3),
      "| all-doomed", len(excess_all), "excess", np.mean(excess_all).round(3), "best Q", np.median(qall).round(3))
