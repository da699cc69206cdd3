"""`qnav bench cluster`: a small fixed study on a local Ray instance with 1 worker, then 2.

Each timing is the study's wall time from its first run started to its last result written, on
a Ray instance already up, its workers started and the training code imported in each (a real
study pays that once per worker for runs of 5-20 minutes; here the runs are seconds long and it
would weigh on the 2-worker case only). The pair is timed `repeats` times, each time in fresh
folders; the report gives each time, the medians and the ratio of the medians (1 worker over 2:
the speed-up).
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from qnav.training.cluster import ClusterSettings, RayEngine, import_ray
from qnav.training.study import Command, RunSpec, StudySettings, run_study

BENCH_SPECS = [RunSpec("walls-inertia", "recurrent", seed) for seed in range(4)]
"""The fixed study: four runs, one torch thread each."""
SMALL_RUN = (
    "train.eval_every_episodes=0",
    "train.final_eval_episodes=8",
    "train.hidden_size=32",
    "train.batch_size=16",
    "train.iterations_per_episode=2",
)
"""A small run but for its length (`train.episodes`, rounds of 8): a small network, no evaluation
during training, an 8-episode test (the cluster tests' runs too)."""
BENCH_SETTINGS = ("train.episodes=24", *SMALL_RUN)
"""Small runs (three rounds of 8 episodes, a short test) so that the pair takes a minute or two."""


def warm_worker() -> int:
    """Import the training code in a Ray worker (held 1 s, so that each of a batch of these
    lands on a worker of its own); returns the worker's pid."""
    import qnav.training.run  # noqa: F401

    time.sleep(1.0)
    return os.getpid()


def time_study(workers: int, root: Path, command: Command) -> float:
    """Seconds the fixed study takes on a local Ray instance with `workers` CPUs."""
    study_engine: list[RayEngine] = []
    settings = ClusterSettings(local_cpus=workers)

    def engine(study: StudySettings) -> RayEngine:
        return study_engine[0]

    study = StudySettings(threads=1, common=BENCH_SETTINGS)
    study_engine.append(RayEngine(root / "runs", study, settings, command))
    try:
        warm = study_engine[0].ray.remote(num_cpus=1)(warm_worker)
        pids = study_engine[0].ray.get([warm.remote() for _ in range(workers)])
        if len(set(pids)) != workers:
            raise RuntimeError(f"warming {workers} workers reached {len(set(pids))} processes")
        started = time.perf_counter()
        run_study(
            BENCH_SPECS,
            root / "runs",
            results_root=root / "results",
            threads=1,
            common=BENCH_SETTINGS,
            engine=engine,
            poll_s=0.2,
        )
        elapsed = time.perf_counter() - started
    finally:
        study_engine[0].close()
    done = len(list((root / "results").glob("*.json")))
    if done != len(BENCH_SPECS):
        raise RuntimeError(f"the bench study finished {done} of {len(BENCH_SPECS)} runs")
    return elapsed


def run(command: Command, repeats: int = 3) -> dict[str, Any]:
    """Time the fixed study on 1 and on 2 workers, `repeats` times each, alternating; each run
    is `command`'s `qnav train` (the shell's `qnav.cli.main`)."""
    times: dict[int, list[float]] = {1: [], 2: []}
    load_before = os.getloadavg()[0]
    for _ in range(repeats):
        for workers in (1, 2):
            with tempfile.TemporaryDirectory(prefix="qnav-bench-cluster-") as folder:
                times[workers].append(time_study(workers, Path(folder), command))
    medians = {w: float(np.median(t)) for w, t in times.items()}
    return {
        "runs": len(BENCH_SPECS),
        "settings": list(BENCH_SETTINGS),
        "repeats": repeats,
        "seconds": {str(w): [round(x, 2) for x in t] for w, t in times.items()},
        "median_s": {str(w): round(m, 2) for w, m in medians.items()},
        "speedup_1_over_2": round(medians[1] / medians[2], 3),
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "load_average_1min_before": round(load_before, 2),
            "ray": _ray_version(),
        },
    }


def _ray_version() -> str:
    return str(import_ray().__version__)


def format_report(report: dict[str, Any]) -> str:
    """The report as text."""
    lines = [
        f"fixed study: {report['runs']} runs of walls-inertia, 1 torch thread each "
        f"({', '.join(report['settings'])})",
    ]
    for workers in ("1", "2"):
        times = ", ".join(f"{t:.1f}" for t in report["seconds"][workers])
        label = "1 worker: " if workers == "1" else f"{workers} workers:"
        lines.append(f"{label} median {report['median_s'][workers]:.1f} s ({times})")
    machine = report["machine"]
    lines.append(
        f"machine: {machine['cores']} cores, load average {machine['load_average_1min_before']} "
        "before the bench (other work on the machine slows the 2-worker case most)"
    )
    lines.append(
        f"speed-up, 1 worker over 2 (ratio of medians, {report['repeats']} pairs): "
        f"{report['speedup_1_over_2']:.2f}"
    )
    return "\n".join(lines)
