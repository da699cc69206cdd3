"""`qnav bench policy`: per-decision latency of the onboard runtime, one thread, each backend.

A decision is what the daemon pays per control period: check and encode one scan and run one
step of the policy's graph with the stream's carried state (the windows in progress). The first
decision of an episode, which primes the state with k steps, falls in the untimed warm-up here.
Each backend is timed in its own process, pinned to one core with BLAS and onnxruntime on one
thread, so neither inherits the other's thread pools or caches. Back to back (the default) the
weights stay in the caches; with a gap (`--gap-ms`, a sleep before each timed decision) each
decision pays for what the gap evicted, as the daemon does between scans.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from qnav.contracts.errors import ConfigError

_ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


def time_decisions(
    policy: Path, backend: str, decisions: int, warmup: int, gap_s: float = 0.0
) -> dict[str, Any]:
    """Latency statistics of `decisions` single-stream decisions (after `warmup` untimed), each
    timed one after a sleep of `gap_s`."""
    import numpy as np

    from qnav.controller.policy import PolicyRuntime

    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    runtime = PolicyRuntime(policy, backend=backend)  # type: ignore[arg-type]
    beams = runtime.contract.num_beams
    rng = np.random.default_rng(0)
    scans = rng.uniform(0.2, 8.0, size=(64, beams)).astype(np.float32) if beams else None
    bearing = rng.uniform(-np.pi, np.pi, 64)
    features = np.stack([rng.uniform(0.1, 5.0, 64), np.sin(bearing), np.cos(bearing)], axis=1)
    elapsed = np.empty(decisions)
    for i in range(warmup + decisions):
        scan = None if scans is None else scans[i % 64]
        if gap_s and i >= warmup:
            time.sleep(gap_s)
        start = time.perf_counter()
        runtime.step(scan, features[i % 64])
        if i >= warmup:
            elapsed[i - warmup] = time.perf_counter() - start
    ms = elapsed * 1e3
    return {
        "p50_ms": round(float(np.percentile(ms, 50)), 4),
        "p99_ms": round(float(np.percentile(ms, 99)), 4),
        "mean_ms": round(float(ms.mean()), 4),
        "max_ms": round(float(ms.max()), 4),
        "decisions": decisions,
        "gap_ms": gap_s * 1e3,
    }


def run(
    policy: Path, backends: list[str], decisions: int = 3000, gap_s: float = 0.0
) -> dict[str, Any]:
    """Each backend timed in a fresh single-threaded process (`gap_s`: sleep before each)."""
    if gap_s < 0:
        raise ConfigError(f"--gap-ms = {gap_s * 1e3:g}: give 0 or more")
    results: dict[str, Any] = {}
    for backend in backends:
        command = [
            sys.executable,
            "-m",
            "qnav.controller.bench",
            str(policy),
            backend,
            str(decisions),
            str(gap_s),
        ]
        done = subprocess.run(
            command,
            env=os.environ | _ONE_THREAD,
            capture_output=True,
            text=True,
            check=False,
        )
        if done.returncode:
            results[backend] = {"error": done.stderr.strip().splitlines()[-1:]}
        else:
            results[backend] = json.loads(done.stdout)
    return {
        "policy": str(policy),
        "machine": platform.processor() or platform.machine(),
        "threads": 1,
        "gap_ms": gap_s * 1e3,
        "backends": results,
    }


def format_report(report: dict[str, Any]) -> str:
    """A table of the backends' latencies."""
    lines = [
        f"per-decision latency, one thread, {report['gap_ms']:g} ms between decisions, "
        f"policy {report['policy']}",
        f"{'backend':<12} {'p50 ms':>8} {'p99 ms':>8} {'mean ms':>8} {'max ms':>8}",
    ]
    for backend, stats in report["backends"].items():
        if "error" in stats:
            lines.append(f"{backend:<12} failed: {stats['error']}")
            continue
        lines.append(
            f"{backend:<12} {stats['p50_ms']:>8.3f} {stats['p99_ms']:>8.3f} "
            f"{stats['mean_ms']:>8.3f} {stats['max_ms']:>8.3f}"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    # The child `run` starts: policy, backend, decisions, gap_s (no user types these).
    policy, backend, decisions, gap_s = sys.argv[1:]
    print(json.dumps(time_decisions(Path(policy), backend, int(decisions), 200, float(gap_s))))
