"""`make demo`: a short, visible tour of what works today.

It evaluates the random agent under the paper's test protocol in the four scenarios, draws one
episode to PNG and GIF, and measures the simulator's speed, then says where everything went.
(The full demo, training and running a policy through the whole stack, arrives with the
learner and the onboard daemons.)
"""

from __future__ import annotations

import time
from pathlib import Path

from sim import paper
from sim.bench import steps_per_second
from sim.config import scenario
from sim.evaluate import EvalSettings, RandomAgent, evaluate

OUT = Path("out/demo")


def main() -> int:
    """Run the demo."""
    started = time.perf_counter()
    print("qnav demo: the simulator and the paper's test protocol\n")
    print("1/3  Random agent, 400 test episodes per scenario (paper's Random rows beside ours)")
    rows = []
    for name, theirs in paper.RANDOM.items():
        result = evaluate(
            scenario(name),
            RandomAgent(200, seed=1),
            EvalSettings(episodes=400, num_worlds=200),
            progress=True,
        )
        rows.append(
            f"  {name:<20} ours {result.success:.3f} / {result.collision:.3f} / "
            f"{result.unfinished:.3f}   paper {theirs.success:.3f} / {theirs.collision:.3f} / "
            f"{theirs.unfinished:.3f}"
        )
    print("  success / collision / unfinished")
    print("\n".join(rows))

    print("\n2/3  Drawing one episode of obstacles-inertia with lidar rays")
    try:
        from sim.render import render_episode

        png, gif = render_episode(
            scenario("obstacles-inertia"), RandomAgent(1, seed=3), OUT, seed=3, rays=True
        )
        print(f"  wrote {png}\n  wrote {gif}")
    except RuntimeError as error:
        print(f"  skipped: {error}")

    print("\n3/3  Simulator speed, obstacles-inertia (720 beams, 5 moving obstacles), batch 64")
    rate = steps_per_second(scenario("obstacles-inertia"), 64, seconds=1.5)
    print(f"  {rate['steps_per_second']:,.0f} env-steps per second (median of 7 chunks)")
    print("  full benchmark on one core: qnav bench sim")

    print(f"\ndone in {time.perf_counter() - started:.0f} s; pictures in {OUT}/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
