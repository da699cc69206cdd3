# Ad hoc measurement of issue 19 (2026-12-06); runs against commit the log names (training.sampling.doom_bounds exists there only).
import numpy as np
from pathlib import Path
from qnav.sim.config import scenario
from qnav.training.episode_log import read_rounds
from qnav.training.replay import EpisodeReplay
from qnav.training.sampling import sample
config = scenario("obstacles-inertia")
eps = [e for r in read_rounds(Path("runs/risk/obstacles-inertia-seed0/episodes")) for e in r][-200:]
replay = EpisodeReplay(config, sum(e.pose.shape[0] for e in eps) + 10, 5, obstacle_inputs=True)
for e in eps: replay.add(e)
rng = np.random.default_rng(1)
near, dec, alld = [], [], []
import qnav.training.sampling as S
orig = S.doom_bounds
def spy(replay, now, targets, obstacles_now, **kw):
    c, v, k = obstacles_now
    near.append(np.linalg.norm(c - replay.pose[now, None, :2], axis=-1).min(axis=1) - config.obstacles.radius_m)
    return orig(replay, now, targets, obstacles_now, **kw)
S.doom_bounds = spy
for i in range(12):
    b = sample(replay, 256, rng, "paper", n_step=5, gamma=0.97, obstacle_redraw_probability=1.0, doom_rows=256)
    d = b.doom.doomed; dec.append(d.any(1) & ~d.all(1)); alld.append(d.all(1))
near, dec, alld = np.concatenate(near), np.concatenate(dec), np.concatenate(alld)
for lo, hi in [(0, .3), (.3, .6), (.6, 1), (1, 1.5), (1.5, 2), (2, 3), (3, 99)]:
    m = (near >= lo) & (near < hi)
    print(f"gap {lo}-{hi} m: rows {m.mean():.3f} decisive {dec[m].mean():.3f} all-doomed {alld[m].mean():.3f} share of decisive {dec[m].sum()/dec.sum():.2f}")
