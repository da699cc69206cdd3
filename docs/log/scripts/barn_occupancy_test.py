"""The occupancy student of `barn_occupancy_bc.py` on the test sets, once (never chosen by them):
BARN's 300 and 300 held-out generated caves, under BARN's protocol (`sim.benchmark`), as
`qnav eval --barn` runs a policy; float32 weights in torch, turns committed.

    .venv/bin/python docs/log/scripts/barn_occupancy_test.py WEIGHTS.pt
"""
from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from barn_occupancy_bc import Driver, Student  # noqa: E402

from qnav.contracts.observation import distance_scale_m  # noqa: E402
from qnav.sim.benchmark import run_benchmark  # noqa: E402
from qnav.sim.config import scenario  # noqa: E402

torch.set_num_threads(1)
net = Student()
net.load_state_dict(torch.load(sys.argv[1], weights_only=True))
net.eval()
base = scenario("barn")
for name, layout in (
    ("BARN's 300", replace(base.layout, source="barn", order="cycle")),
    ("held-out caves (300)", replace(base.layout, source="cave", split="test", worlds=300, order="cycle")),
):
    world = replace(base, layout=layout)
    angles = world.lidar.beam_angles_rad()  # type: ignore[union-attr]
    result = run_benchmark(world, Driver(net, angles, 64, distance_scale_m(world.lidar)), "occupancy", 64)  # type: ignore[arg-type]
    print(f"{name}: success {result.success:.3f} collision {result.collision:.3f} timeout {result.timeout:.3f}"
          f" metric {result.metric:.3f} loops {getattr(result, 'loops', float('nan')):.3f}", flush=True)
