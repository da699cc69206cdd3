"""Pictures of training: success during training, as in the paper's figures 5, 6, 8 and 9."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_training(history: list[dict[str, float]], path: Path, title: str) -> Path:
    """Validation success (and the training episodes' success, smoothed) against episodes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(6.4, 4.0), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    episodes = np.array([row["episodes"] for row in history])
    train = np.array([row["train_success"] for row in history])
    # Trailing mean over the last few rounds: each point uses only episodes up to it.
    window = 6
    cumulative = np.concatenate([[0.0], np.cumsum(train)])
    first = np.maximum(0, np.arange(1, len(train) + 1) - window)
    smoothed = (cumulative[1:] - cumulative[first]) / (np.arange(1, len(train) + 1) - first)
    axes.plot(episodes, smoothed, color="0.6", label="training episodes (with exploration)")
    evaluated = [row for row in history if "eval_success" in row]
    axes.plot(
        [row["episodes"] for row in evaluated],
        [row["eval_success"] for row in evaluated],
        marker="o",
        color="tab:blue",
        label="greedy validation (separate layouts)",
    )
    axes.set_xlabel("training episodes")
    axes.set_ylabel("success fraction")
    axes.set_ylim(-0.02, 1.02)
    axes.grid(alpha=0.3)
    axes.legend(loc="lower right")
    axes.set_title(title)
    figure.tight_layout()
    partial = path.with_suffix(".partial.png")
    figure.savefig(partial)
    partial.replace(path)
    return path
