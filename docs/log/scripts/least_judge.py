# Ad hoc measurement of issue 19 (2026-12-06); runs against commit 0475843 and later.
"""A judge of the shield's rule, learned: fit P(action is among the least colliding) instead of
P(action is not doomed), from the collision shares a label folder already holds, and export it as
a judge file (the controller's judge rule then keeps the policy's action unless the fit doubts it
is among the least colliding: the shield's rule with learned risks).

Usage: least_judge.py FOLDER JUDGE_FILE_LIKE OUT_PREFIX TOLERANCE THRESHOLD[,THRESHOLD...] [NEAR]
(NEAR: label "unsafe" where at least that share of the continuations collide, instead)
(all labelled states of every round, not only the doom-decisive ones the label fit keeps)
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import onnx
import torch

from qnav.contracts.judge_file import JudgeContract
from qnav.lab.decisive import DecisiveStates, is_decisive
from qnav.lab.doubt import LABEL_PROBE, LabelFolder
from qnav.lab.judge import export_judge
from qnav.lab.probe import doom_network, fit_doom, slot_features
from qnav.sim.config import SCENARIOS


def main() -> None:
    torch.set_num_threads(1)
    folder, like, prefix = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    tolerance, thresholds = float(sys.argv[4]), [float(t) for t in sys.argv[5].split(",")]
    store = LabelFolder(folder)
    base = DecisiveStates.load(store.round_path(0))
    rounds = list(store.rounds())
    context = [slot_features(base)[0]] + [r.context for r in rounds]
    slots = [slot_features(base)[1]] + [r.slots for r in rounds]
    shares = np.concatenate([base.collide_share] + [r.collide_share for r in rounds])
    inputs = (torch.from_numpy(np.concatenate(context)), torch.from_numpy(np.concatenate(slots)))
    least = shares <= shares.min(axis=1, keepdims=True) + tolerance
    pseudo = np.where(least, 0.0, 1.0)  # "doomed" = not among the least colliding
    if len(sys.argv) > 6:  # near doom instead: "doomed" = at least this share of them collide
        pseudo = np.where(shares >= float(sys.argv[6]), 1.0, 0.0)
    differ = is_decisive(pseudo == 1.0)
    print(f"{len(shares)} states, {differ.sum()} where the least colliding actions are not all "
          f"({is_decisive(shares == 1.0).sum()} doom-decisive)", flush=True)
    contract = JudgeContract.from_metadata(
        {p.key: p.value for p in onnx.load(like).metadata_props}, str(like)
    )
    world = SCENARIOS[contract.scenario]
    network = doom_network(world, "slots")
    started = time.time()
    fit_doom(network, inputs, pseudo, LABEL_PROBE)
    print(f"fitted in {(time.time() - started) / 60:.1f} min", flush=True)
    for threshold in thresholds:
        path = Path(f"{prefix}-t{threshold:g}.onnx")
        export_judge(network, dataclasses.replace(contract, threshold=threshold), path)
        print(path, flush=True)


if __name__ == "__main__":
    main()
