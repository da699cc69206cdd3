"""`digest.py RUNS_DIR`: a stable digest (JSON) of everything the runs in RUNS_DIR wrote, less
timings: progress, results, every tensor of the networks, optimiser and snapshots, every array
of the episode files, and the evaluations beside them (`run.sh` compares two)."""

from __future__ import annotations

import csv
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch

TIMINGS = {"collect_s", "train_s", "eval_s", "commit"}
RETIRED = {"decisive", "decisive_safe", "decisive_balanced"}
"""What the decisive-state gauge added (issue 54 retired it): left out, so trees from before
and after compare."""


def _hash(array: Any) -> str:
    value = array.detach().cpu().numpy() if torch.is_tensor(array) else array
    data = np.ascontiguousarray(value)
    raw = data.tobytes() + str(data.dtype).encode() + str(data.shape).encode()
    return hashlib.sha256(raw).hexdigest()[:16]


def _tree(value: Any) -> Any:
    if torch.is_tensor(value) or isinstance(value, np.ndarray):
        return _hash(value)
    if isinstance(value, dict):
        return {str(k): _tree(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_tree(v) for v in value]
    return value


def _untimed(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in row.items() if k != "wall_s" and k not in RETIRED} for row in rows]


def digest(run: Path) -> dict[str, Any]:
    """Everything one run folder holds that a seeded run must reproduce."""
    with (run / "progress.csv").open() as file:
        found: dict[str, Any] = {"progress": _untimed(list(csv.DictReader(file)))}
    results = json.loads((run / "results.json").read_text())
    found["results"] = {k: v for k, v in results.items() if k not in TIMINGS | RETIRED}
    found["model"] = _tree(torch.load(run / "model.pt", weights_only=False)["online"])
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=False)
    found["checkpoint"] = {k: _tree(checkpoint[k]) for k in ("online", "target", "optimizer")}
    progress = {k: v for k, v in checkpoint["progress"].items() if k not in TIMINGS}
    progress["history"] = _untimed(progress["history"])
    found["checkpoint_progress"] = progress
    rounds = {}
    for path in sorted((run / "episodes").glob("*.npz")):
        with np.load(path) as data:
            # `demonstrated` went with the demonstrations (issue 22); older files still hold it.
            rounds[path.name] = {
                k: _hash(data[k]) for k in sorted(data.files) if k != "demonstrated"
            }
    found["episodes"] = rounds
    if (run / "best.pt").exists():
        found["best.pt"] = _tree(torch.load(run / "best.pt", weights_only=False)["online"])
    snapshots = run / "snapshots"
    if snapshots.exists():
        found["snapshots"] = {
            p.name: _tree(torch.load(p, weights_only=False)) for p in sorted(snapshots.iterdir())
        }
    return found


def main(root: Path) -> None:
    out: dict[str, Any] = {run.name: digest(run) for run in sorted(root.iterdir()) if run.is_dir()}
    for path in sorted(root.glob("eval-*.json")):
        out[path.name] = json.loads(path.read_text())
    print(json.dumps(out, indent=1, sort_keys=True))


if __name__ == "__main__":
    main(Path(sys.argv[1]))
