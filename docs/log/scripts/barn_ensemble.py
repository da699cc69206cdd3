"""Gauge: several BARN policy files deciding together (the mean of their action probabilities,
softmax of each file's outputs, then the files' turn commitment), on generated cave validation
worlds (never BARN's), beside each file alone.

    .venv/bin/python docs/log/scripts/barn_ensemble.py WORLDS A.onnx B.onnx [...]
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.actions import TurnCommitment
from qnav.contracts.motion import Outcome
from qnav.controller.policy import PolicyRuntime
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings, episode_outcomes
from qnav.sim.world import Observation


def softmax(q: NDArray[np.float32]) -> NDArray[np.float64]:
    z = np.exp(q - q.max(axis=1, keepdims=True))
    return np.asarray(z / z.sum(axis=1, keepdims=True), dtype=np.float64)


class Ensemble:
    """Files stepped side by side; the mean of their probabilities decides."""

    def __init__(self, files: list[Path], streams: int) -> None:
        self.runtimes = [PolicyRuntime(f, num_streams=streams) for f in files]
        self.turns = TurnCommitment(streams)
        self.last_q = np.zeros((streams, 3), dtype=np.float32)

    def start(self, worlds: NDArray[np.intp], episodes: NDArray[np.int64]) -> None:
        for runtime in self.runtimes:
            runtime.reset(worlds)
        self.turns.restart(worlds)

    def act(self, observation: Observation) -> NDArray[np.int64]:
        probabilities = np.mean(
            [
                softmax(r.step_batch(observation.scan_m, observation.target_features())[1])
                for r in self.runtimes
            ],
            axis=0,
        )
        self.last_q = probabilities.astype(np.float32)
        return self.turns(probabilities.argmax(axis=1))


def main() -> None:
    count, files = int(sys.argv[1]), [Path(a) for a in sys.argv[2:]]
    base = scenario("cave")
    world = replace(base, layout=replace(base.layout, split="validation", worlds=count, order="cycle"))
    settings = EvalSettings(episodes=count, num_worlds=64, seed=0)
    for group in [[f] for f in files] + [files]:
        started = time.perf_counter()
        outcomes, _ = episode_outcomes(world, Ensemble(group, 64), settings)  # type: ignore[arg-type]
        shares = [np.mean(outcomes == k) for k in (Outcome.SUCCESS, Outcome.COLLISION, Outcome.RUNNING)]
        names = "+".join(f.parent.name for f in group)
        print(
            f"{names}: success {shares[0]:.3f} collision {shares[1]:.3f} timeout {shares[2]:.3f}"
            f" ({time.perf_counter() - started:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
