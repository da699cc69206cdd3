"""The BARN table of docs/results.md, from `results/barn/*.json`.

Each file is one `qnav eval --barn ... --json` (all 300 worlds, one run each), saved as
`results/barn/ROW.json` for a baseline (`goto.json`, `dwa.json`, ...) or
`results/barn/ROW-seedK.json` for one training run of a learner; the seeds of a row are
averaged. A run folder evaluated with `--policy RUN` carries its training cost (`training`:
episodes and minutes), which the table shows.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

BARN_FOLDER = "barn"
"""Under the results folder."""

BARN_DWA_PUBLISHED = {"success": 0.88, "collision": 0.048, "timeout": 0.072, "metric": 0.169}
"""BARN's own move_base + DWA in Gazebo: 50 worlds x 10 runs (the challenge's README)."""

COLUMNS = ("success", "collision", "timeout", "metric", "loops")
"""The shares and means each row gives."""

_SEED = re.compile(r"^(?P<row>.+)-seed(?P<seed>\d+)$")


def barn_rows(folder: Path) -> dict[str, list[dict[str, Any]]]:
    """Each row's results (one per seed), rows in file-name order."""
    rows: dict[str, list[dict[str, Any]]] = {}
    for path in sorted(folder.glob("*.json")):
        match = _SEED.match(path.stem)
        name = match["row"] if match else path.stem
        rows.setdefault(name, []).append(json.loads(path.read_text()))
    return rows


def _cell(values: list[float]) -> str:
    """One value, or 'mean +- std' over seeds."""
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{np.mean(values):.3f} +- {np.std(values):.3f}"


def _training_cell(results: list[dict[str, Any]]) -> str:
    """'episodes / minutes' (the most over seeds), or blank for a baseline."""
    training = [r["training"] for r in results if "training" in r]
    if not training:
        return ""
    episodes = max(t["episodes"] for t in training)
    minutes = max(t["minutes"] for t in training)
    return f"{episodes} / {minutes:.0f}"


def barn_table(rows: dict[str, list[dict[str, Any]]]) -> list[str]:
    """The table's lines: one row per file or per seeds of a learner (`barn_rows`), then BARN's
    own DWA."""
    header = ["agent", "n", *COLUMNS, "training episodes / minutes", "what drove"]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for name, results in rows.items():
        cells = [_cell([float(r[key]) for r in results]) for key in COLUMNS]
        what = str(results[0].get("agent", ""))
        lines.append(
            f"| {name} | {len(results)} | " + " | ".join(cells)
            + f" | {_training_cell(results)} | {what} |"
        )  # fmt: skip
    published = BARN_DWA_PUBLISHED
    lines.append(
        "| BARN's move_base + DWA (Gazebo, context) | 500 runs | "
        + " | ".join(f"{published[k]:.3f}" for k in ("success", "collision", "timeout", "metric"))
        + " | | | another simulator and robot, a costmap and a global planner |"
    )
    return lines


SHIPPED = "dagger-recurrent-committed"
"""The row of the policy as shipped: the recurrent learner's files, turns committed."""

BARN_GOALS = (
    (SHIPPED, None, 0.90, "the recurrent policy >= 0.90"),
    (SHIPPED, "dwa", 0.05, "the recurrent policy >= 0.05 above DWA"),
    (SHIPPED, "goto", 0.40, "the recurrent policy >= 0.40 above blind go-to-target"),
    (SHIPPED, "dagger-feedforward-committed", 0.05, "recurrent >= 0.05 above feedforward"),
)
"""Issue 52's goals on BARN's success: (row, the row it is compared with or None, the margin or
level, what it says)."""


def barn_goals(rows: dict[str, list[dict[str, Any]]]) -> list[str]:
    """One line per goal whose rows are saved: met or not, with the numbers (seeds' means)."""
    mean = {name: float(np.mean([r["success"] for r in results])) for name, results in rows.items()}
    lines = []
    for row, other, margin, says in BARN_GOALS:
        if row not in mean or (other is not None and other not in mean):
            continue
        wanted = margin if other is None else mean[other] + margin
        verdict = "met" if mean[row] >= wanted else "**not met**"
        against = "" if other is None else f" against {other} {mean[other]:.3f}"
        lines.append(f"- {says}: {mean[row]:.3f}{against}, {verdict} (goal {wanted:.3f})")
    return lines


def barn_lines(results_root: Path) -> list[str]:
    """docs/results.md's BARN section (nothing where no result is saved)."""
    rows = barn_rows(results_root / BARN_FOLDER)
    if not rows:
        return []
    return [
        "",
        "## BARN: 300 cluttered worlds (docs/barn.md)",
        "",
        "One run per world under BARN's protocol (`qnav eval --barn`), the 0.3 m disc and the",
        "paper's robot; each row `qnav eval --barn --agent NAME --json > results/barn/NAME.json`",
        "or, for a training run, `qnav eval --barn --policy RUN --json >",
        "results/barn/ROW-seedK.json` (`-committed` rows: the run's int8 policy file with turn",
        "commitment, `qnav export RUN -o FILE --weights int8 --turn-commitment`, in place of",
        "RUN). Training worlds are generated (docs/barn.md): nothing here was trained or tuned",
        "on BARN's worlds. loops: runs that came back to a place they had left.",
        "",
        *barn_table(rows),
        "",
        *barn_goals(rows),
    ]
