"""`qnav bench learner`: how much of the machine one training iteration uses.

The iteration's floating-point work is counted by torch's own FLOP counter (matrix products and
convolutions, forward and backward), its time is the median over repeated iterations, and the
machine's reference is its own large float32 matrix product at the same thread count (the
fastest of several).
"""

from __future__ import annotations

import platform
import time
from typing import Any

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from qnav.sim.config import scenario
from qnav.training.algorithm import td_update
from qnav.training.networks import QNetwork
from qnav.training.replay import Batch


def matmul_gflops(size: int = 2048, repeats: int = 20, dtype: torch.dtype = torch.float32) -> float:
    """GFLOP/s of the fastest of `repeats` size x size matrix products.

    The fastest, not the median: on a shared machine a neighbour's burst slows some repeats,
    and the reference should be what the cores can do, so that a share of it never exceeds 1.
    """
    a = torch.rand(size, size).to(dtype)
    b = torch.rand(size, size).to(dtype)
    for _ in range(3):
        a @ b
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - start)
    return 2 * size**3 / min(times) / 1e9


def _batch(network: QNetwork, batch_size: int, window: int) -> Batch:
    rng = np.random.default_rng(0)
    return Batch(
        frames=rng.random((batch_size, window + 1, network.frame_size), dtype=np.float32),
        action=rng.integers(0, 3, batch_size),
        reward=rng.random(batch_size, dtype=np.float32),
        terminal=rng.random(batch_size) < 0.1,
        steps=np.ones(batch_size, dtype=np.int64),
        discount=np.full(batch_size, 0.97, dtype=np.float32),
    )


def run(
    *,
    model: str = "recurrent",
    scenario_name: str = "obstacles-inertia",
    batch_size: int = 256,
    window: int = 5,
    repeats: int = 10,
    threads: int = 2,
) -> dict[str, Any]:
    """Time and count one training iteration of the paper-sized network."""
    torch.set_num_threads(threads)
    world = scenario(scenario_name)
    beams = world.lidar.num_beams if world.lidar else None
    online = QNetwork(model, beams)  # type: ignore[arg-type]
    target = QNetwork(model, beams)  # type: ignore[arg-type]
    optimizer = torch.optim.Adam(online.parameters(), lr=1e-4)
    batch = _batch(online, batch_size, window)
    counter = FlopCounterMode(display=False)
    with counter:
        td_update(online, target, optimizer, batch, window=window)
    flops = counter.get_total_flops()
    machine = matmul_gflops()
    report: dict[str, Any] = {
        "model": model,
        "batch": batch_size,
        "window": window,
        "threads": threads,
        "gflop_per_iteration": flops / 1e9,
        "machine_matmul_gflops_fp32": machine,
        "machine_matmul_gflops_bf16": matmul_gflops(dtype=torch.bfloat16),
        "precisions": {},
        "machine": {"cpu": platform.processor() or platform.machine(), "torch": torch.__version__},
    }
    for name, bf16 in (("fp32", False), ("bf16_autocast", True)):
        for _ in range(3):
            td_update(online, target, optimizer, batch, window=window, bf16=bf16)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            td_update(online, target, optimizer, batch, window=window, bf16=bf16)
            times.append(time.perf_counter() - start)
        median = float(np.median(times))
        report["precisions"][name] = {
            "iteration_ms_p50": median * 1e3,
            "iteration_ms_p99": float(np.percentile(times, 99)) * 1e3,
            "achieved_gflops": flops / median / 1e9,
            "fraction_of_fp32_matmul": flops / median / 1e9 / machine,
        }
    return report


def format_report(report: dict[str, Any]) -> str:
    """The report as text."""
    lines = [
        f"{report['model']} Q-network, batch {report['batch']}, window {report['window']}, "
        f"{report['threads']} threads",
        f"work per training iteration: {report['gflop_per_iteration']:.2f} GFLOP "
        "(forward, backward, two target forwards)",
        f"machine: {report['machine_matmul_gflops_fp32']:.0f} GFLOP/s float32 matrix product, "
        f"{report['machine_matmul_gflops_bf16']:.0f} GFLOP/s bfloat16",
        "",
        f"{'precision':<15} {'ms p50':>8} {'ms p99':>8} {'GFLOP/s':>8} {'of fp32 peak':>13}",
    ]
    for name, row in report["precisions"].items():
        lines.append(
            f"{name:<15} {row['iteration_ms_p50']:>8.1f} {row['iteration_ms_p99']:>8.1f} "
            f"{row['achieved_gflops']:>8.1f} {row['fraction_of_fp32_matmul']:>12.0%}"
        )
    return "\n".join(lines)
