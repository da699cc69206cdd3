# Ad hoc measurement of issue 53 (2026-12-07); runs against the commit adding the proximity stop
# (controller/proximity.py), and later.
"""What the proximity stop costs the shielded policy in the simulator: the test protocol's
episodes of a policy file with the controller's look ahead in process (`qnav eval --policy FILE
--lookahead shield`), without the proximity stop and with each field asked for, the same
episodes for each.

Usage: proximity_eval.py POLICY.onnx EPISODES VARIANT[,VARIANT...] [OUT.jsonl]
VARIANT: "off" (no proximity stop) or "FOOTPRINT/TRAVEL" in metres (`proximity.footprint_m`,
`proximity.travel_m`; the defaults are 0.5/0.35). Prints success, collision and unfinished per
variant; with OUT, appends each variant's outcome per episode (1 success, 2 collision, 0 neither).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from qnav.controller.perception import TrackerSettings
from qnav.controller.policy import PolicyRuntime
from qnav.controller.proximity import ProximitySettings
from qnav.sim.config import scenario
from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent, episode_outcomes
from qnav.tracking import LookaheadAgent, lookahead_settings


def main() -> None:
    policy, episodes, variants = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3].split(",")
    out = Path(sys.argv[4]) if len(sys.argv) > 4 else None
    world = scenario(PolicyRuntime(policy).contract.scenario)
    settings = EvalSettings(episodes=episodes)
    worlds = min(settings.num_worlds, episodes)
    for variant in variants:
        proximity = None
        if variant != "off":
            footprint, travel = (float(v) for v in variant.split("/"))
            proximity = ProximitySettings(footprint_m=footprint, travel_m=travel)
        inner = StreamPolicyAgent(PolicyRuntime(policy, num_streams=worlds), worlds)
        agent = LookaheadAgent(
            inner,
            world,
            worlds,
            tracker=TrackerSettings(),
            lookahead=lookahead_settings("shield", None),
            proximity=proximity,
            seed=settings.seed,
        )
        started = time.time()
        outcomes, _ = episode_outcomes(world, agent, settings)
        row = {
            "variant": variant,
            "success": float(np.mean(outcomes == 1)),
            "collision": float(np.mean(outcomes == 2)),
            "unfinished": float(np.mean(outcomes == 0)),
            "minutes": round((time.time() - started) / 60, 1),
        }
        print(json.dumps(row), flush=True)
        if out is not None:
            with out.open("a") as file:
                file.write(json.dumps(row | {"outcomes": outcomes.tolist()}) + "\n")


if __name__ == "__main__":
    main()
