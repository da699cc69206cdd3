"""`make demo`: train a policy, export it, and drive the simulated car with the whole stack.

1. Train the paper's recurrent Q-network on walls-increment (64 episodes; a couple of minutes).
2. Export it to one ONNX file, which is then tested under the paper's protocol by the onboard
   runtime.
3. Start the full stack as separate processes on loopback: the simulator playing the car
   (`qnav sim-car`), the controller daemon, the MAVLink bridge and the recorder; run episodes.
4. Print the stack's results beside the same episodes run in process and the paper's row, and
   write a trajectory picture (PNG, GIF) and the MCAP recording.

Everything goes to out/demo/. A second run reuses the trained run and starts from step 2.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

from qnav.sim import paper
from qnav.sim.config import scenario

OUT = Path("out/demo")
SCENARIO = "walls-increment"
TRAIN_EPISODES = 64
STACK_EPISODES = 20


def _step(number: int, text: str) -> None:
    print(f"\n{number}/4  {text}", flush=True)


def main() -> int:
    """Run the demo."""
    from qnav.controller.policy import PolicyRuntime
    from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent, evaluate
    from qnav.simcar.car import EpisodeLog, episode_record
    from qnav.stack import run_stack
    from qnav.training.config import preset
    from qnav.training.export import export_run
    from qnav.training.run import train

    started = time.perf_counter()
    world = scenario(SCENARIO)
    print(f"qnav demo: learn {SCENARIO}, export the policy, drive the car through the full stack")

    _step(1, f"Training the recurrent Q-network, {TRAIN_EPISODES} episodes of {SCENARIO}")
    settings = replace(
        preset("fast", world),
        episodes=TRAIN_EPISODES,
        eval_every_episodes=32,
        eval_episodes=50,
    )
    run_dir = OUT / "run"
    results = train(world, settings, run_dir, progress=True)
    test = results["test"]
    print(
        f"  torch network, test protocol (200 episodes): success {test['success']:.3f}, "
        f"collision {test['collision']:.3f}, unfinished {test['unfinished']:.3f}"
    )

    _step(2, "Exporting to ONNX and testing the file with the onboard runtime")
    policy = OUT / "policy.onnx"
    contract = export_run(run_dir, policy, progress=True)
    tested = contract.evaluation
    print(
        f"  wrote {policy}: success {tested['success']:.3f}, collision "
        f"{tested['collision']:.3f} over {int(tested['episodes'])} episodes"
    )

    _step(3, f"Full stack: sim-car, controller, bridge, recorder; {STACK_EPISODES} episodes")
    stack = run_stack(policy, OUT / "stack", episodes=STACK_EPISODES, progress=True)
    same = evaluate(
        world,
        StreamPolicyAgent(PolicyRuntime(policy, num_streams=STACK_EPISODES), STACK_EPISODES),
        EvalSettings(episodes=STACK_EPISODES, num_worlds=STACK_EPISODES),
    )

    _step(4, "Results and pictures")
    theirs, _ = paper.RECURRENT[SCENARIO]
    rows = [
        ("full stack (separate processes)", stack["success"], stack["collision"],
         stack["unfinished"], stack["episodes"]),
        ("same episodes in process", same.success, same.collision, same.unfinished,
         same.episodes),
        ("policy file, test protocol", tested["success"], tested["collision"],
         tested["unfinished"], int(tested["episodes"])),
        ("paper, Table III recurrent", theirs.success, theirs.collision, theirs.unfinished, 200),
    ]  # fmt: skip
    print(f"  {'':<34} {'success':>8} {'collision':>10} {'unfinished':>11} {'episodes':>9}")
    for label, success, collision, unfinished, count in rows:
        print(f"  {label:<34} {success:>8.3f} {collision:>10.3f} {unfinished:>11.3f} {count:>9}")

    logs = [json.loads(line) for line in (OUT / "stack" / "episodes.jsonl").read_text().split("\n")
            if line]  # fmt: skip
    try:
        from qnav.sim.render import draw_gif, draw_png

        record = episode_record(world, EpisodeLog(**logs[0]))
        png = draw_png(record, OUT / "stack-episode-0.png")
        gif = draw_gif(record, OUT / "stack-episode-0.gif")
        print(f"  trajectory of the stack's first episode: {png} and {gif}")
    except RuntimeError as error:
        print(f"  pictures skipped: {error}")
    for path in stack["recording"]:
        print(f"  MCAP recording (open it in Foxglove): {path}")
    print(f"  daemon configurations and logs: {OUT / 'stack'}/")
    print(f"\ndone in {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
