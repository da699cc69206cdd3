"""`make demo`: learn a policy, drive the simulated car with the whole stack, then watch the
shipped controller dodge moving obstacles.

1. Train the paper's recurrent Q-network on walls-increment (64 episodes; a couple of minutes)
   and export it to one ONNX file, tested under the paper's protocol by the onboard runtime.
2. Start the full stack as separate processes on loopback, the simulator playing the car
   (`qnav sim-car`, the controller daemon, the MAVLink bridge, the recorder), and drive a few
   episodes with the new file.
3. Among five moving obstacles: the committed obstacles-inertia policy
   (`tests/data/stack/obstacles-inertia.onnx`) alone, then under the shield with the proximity
   stop, as `config/controller.toml` ships the controller (`qnav eval --lookahead shield`);
   evaluated in the background while step 2's stack, which mostly waits, drives.
4. Pictures: the training curve, the stack's first episode, and one obstacle episode the policy
   alone loses and the shielded controller wins.

Everything goes to out/demo/. A second run reuses the trained run.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import replace
from pathlib import Path
from typing import IO, TYPE_CHECKING, NamedTuple, cast

from qnav.sim import paper
from qnav.sim.config import WorldConfig, scenario

if TYPE_CHECKING:
    from qnav.sim.evaluate import Agent
    from qnav.sim.render import EpisodeRecord

OUT = Path("out/demo")
SCENARIO = "walls-increment"
TRAIN_EPISODES = 64
STACK_EPISODES = 10
OBSTACLES_POLICY = Path("tests/data/stack/obstacles-inertia.onnx")
OBSTACLE_EPISODES = 50
"""The first 50 test episodes, those of docs/deploy.md's stack figures (0.500 alone, 0.880
shielded with the proximity stop, through the full stack)."""
PICTURE_TRIES = 20
"""Episodes tried for a picture that the policy alone loses and the shielded controller wins."""


class _Steps:
    """The demo's numbered steps, each timed: a user sees where the minutes go."""

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.starts: list[tuple[str, float]] = []
        """Each step's name and when it began."""

    def next(self, number: int, name: str, text: str) -> None:
        self.starts.append((name, time.perf_counter()))
        print(f"\n{number}/4  {text}", flush=True)

    def summary(self) -> str:
        now = time.perf_counter()
        ends = [began for _, began in self.starts[1:]] + [now]
        laps = ", ".join(
            f"{name} {end - began:.0f} s"
            for (name, began), end in zip(self.starts, ends, strict=True)
        )
        return f"done in {now - self.started:.0f} s ({laps})"


def main() -> int:
    """Run the demo."""
    from qnav.stack import sigterm_interrupts

    steps = _Steps()
    print("qnav demo: learn walls-increment, drive the car through the full stack, then dodge")
    steps.next(
        1, "training", f"Training the recurrent Q-network, {TRAIN_EPISODES} episodes of {SCENARIO}"
    )
    policy, tested = _train_and_export()
    steps.next(
        2, "stack", f"Full stack: sim-car, controller, bridge, recorder; {STACK_EPISODES} episodes"
    )
    with sigterm_interrupts(), _background(OBSTACLE_COMMANDS) as evaluations:
        pictures = _drive_the_stack(policy, tested)
        steps.next(
            3,
            "obstacles",
            f"Moving obstacles: {OBSTACLES_POLICY} alone, then shielded (as shipped)",
        )
        _report(evaluations)
        print(
            "\n  the same through the full stack (docs/deploy.md; about 6 minutes each):"
            f"\n  $ qnav stack --policy {OBSTACLES_POLICY} --episodes 50 --lookahead off|shield"
        )
    steps.next(4, "pictures", "Pictures")
    pictures += _dodge_pictures()
    for label, path in pictures:
        print(f"  {label:<42} {path}")
    print(f"\n{steps.summary()}")
    return 0


def _train_and_export() -> tuple[Path, Mapping[str, float]]:
    """The walls policy trained (or the run found) and exported; its file and test figures."""
    from qnav.training.config import preset
    from qnav.training.export import export_run
    from qnav.training.run import train

    world = scenario(SCENARIO)
    settings = replace(
        preset("fast", world), episodes=TRAIN_EPISODES, eval_every_episodes=32, eval_episodes=50
    )
    results = train(world, settings, OUT / "run", progress=True)
    test = results["test"]
    print(
        f"  torch network, test protocol (200 episodes): success {test['success']:.3f}, "
        f"collision {test['collision']:.3f}, unfinished {test['unfinished']:.3f}"
    )
    print("  exporting to ONNX and testing the file with the onboard runtime")
    policy = OUT / "policy.onnx"
    tested = export_run(OUT / "run", policy, progress=True).evaluation
    print(
        f"  wrote {policy}: success {tested['success']:.3f}, collision "
        f"{tested['collision']:.3f} over {int(tested['episodes'])} episodes"
    )
    return policy, tested


def _drive_the_stack(policy: Path, tested: Mapping[str, float]) -> list[tuple[str, Path]]:
    """The new file through the full stack beside the same episodes in process; the pictures
    this step leaves."""
    from qnav.controller.policy import PolicyRuntime
    from qnav.sim.evaluate import EvalSettings, StreamPolicyAgent, evaluate
    from qnav.stack import run_stack

    stack = run_stack(policy, OUT / "stack", episodes=STACK_EPISODES, progress=True)
    same = evaluate(
        scenario(SCENARIO),
        StreamPolicyAgent(PolicyRuntime(policy, num_streams=STACK_EPISODES), STACK_EPISODES),
        EvalSettings(episodes=STACK_EPISODES, num_worlds=STACK_EPISODES),
    )
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
    pictures = [("training curve", OUT / "run" / "success.png")]
    pictures += _stack_pictures()
    pictures += [
        (f"MCAP recording (Foxglove) {i}", Path(p)) for i, p in enumerate(stack["recording"])
    ]
    return [*pictures, ("daemon configurations and logs", OUT / "stack")]


def _stack_pictures() -> list[tuple[str, Path]]:
    """The stack's first episode as PNG and GIF (none without matplotlib)."""
    from qnav.simcar.car import EpisodeLog, episode_record

    lines = (OUT / "stack" / "episodes.jsonl").read_text().splitlines()
    record = episode_record(scenario(SCENARIO), EpisodeLog(**json.loads(lines[0])))
    return _drawn(record, OUT / "stack-episode-0", "the stack's first episode")


OBSTACLE_COMMANDS = tuple(
    [
        "eval",
        "--policy",
        str(OBSTACLES_POLICY),
        f"--episodes={OBSTACLE_EPISODES}",
        f"--lookahead={mode}",
    ]
    for mode in ("off", "shield")
)
"""Step 3's evaluations: the committed obstacles policy alone, then as shipped."""


class Evaluation(NamedTuple):
    """A `qnav` command line, the child process running it and the file of its stderr."""

    argv: list[str]
    process: subprocess.Popen[str]
    errors: IO[str]


@contextmanager
def _background(commands: Sequence[list[str]]) -> Iterator[list[Evaluation]]:
    """`qnav` commands in child processes, killed on the way out if still running. Step 3 runs
    beside the stack: the stack waits on its daemons' clocks (a tenth of a core), the
    evaluations need the CPU, so together they take the stack's minute."""
    from qnav.stack import qnav_child

    runs: list[Evaluation] = []
    with ExitStack() as files:
        try:
            for argv in commands:
                # stderr (progress bars) to a file: nothing reads the pipes until the stack is
                # done, and a full pipe would stall the child.
                errors = files.enter_context(tempfile.TemporaryFile("w+"))
                process = qnav_child(argv, stdout=subprocess.PIPE, stderr=errors)
                runs.append(Evaluation(list(argv), process, errors))
            yield runs
        finally:
            for run in runs:
                if run.process.poll() is None:
                    run.process.kill()
                    run.process.wait()


def _report(evaluations: list[Evaluation]) -> None:
    """Each command and what it printed, once it is done; a failed one raises with its errors."""
    for argv, process, errors in evaluations:
        printed, _ = process.communicate()
        print(f"\n  $ qnav {' '.join(argv)}\n{printed}", end="", flush=True)
        if process.returncode != 0:
            errors.seek(0)
            raise RuntimeError(
                f"qnav {' '.join(argv)} exited with {process.returncode}:\n{errors.read()}"
            )


def _dodge_pictures() -> list[tuple[str, Path]]:
    """The first test episode the policy alone loses and the shielded controller wins, drawn
    both ways."""
    from qnav.sim.evaluate import EvalSettings
    from qnav.sim.render import record_episode

    world = scenario("obstacles-inertia")
    seed = EvalSettings().seed
    for episode in range(PICTURE_TRIES):
        alone = record_episode(world, _obstacles_agent(world, "off"), seed, episode)
        if alone.outcome_label != "collision":
            continue
        shielded = record_episode(world, _obstacles_agent(world, "shield"), seed, episode)
        if shielded.outcome_label == "success":
            stem = OUT / f"obstacles-episode-{episode}"
            return [
                *_drawn(alone, stem.with_name(stem.name + "-alone"), f"episode {episode}, alone"),
                *_drawn(shielded, stem.with_name(stem.name + "-shielded"), "the same, shielded"),
            ]
    print(f"  no episode among the first {PICTURE_TRIES} lost alone and won shielded")
    return []


def _obstacles_agent(world: WorldConfig, mode: str) -> Agent:
    """The committed obstacles policy on one world, alone ("off") or under the look ahead in
    `mode` with the proximity stop, as `qnav eval --lookahead` runs it."""
    from qnav.controller.perception import TrackerSettings
    from qnav.controller.policy import PolicyRuntime
    from qnav.sim.evaluate import StreamPolicyAgent
    from qnav.tracking import LookaheadAgent, QAgent, fitted_proximity, lookahead_settings

    agent = StreamPolicyAgent(PolicyRuntime(OBSTACLES_POLICY, num_streams=1), 1)
    if mode == "off":
        return agent
    return LookaheadAgent(
        cast(QAgent, agent),
        world,
        1,
        tracker=TrackerSettings(),
        lookahead=lookahead_settings(mode),
        proximity=fitted_proximity(world),
    )


def _drawn(record: EpisodeRecord, stem: Path, label: str) -> list[tuple[str, Path]]:
    """The episode as `stem`.png and `stem`.gif, labelled; none without matplotlib."""
    from qnav.sim.render import draw_gif, draw_png

    try:
        png = draw_png(record, stem.with_suffix(".png"))
        gif = draw_gif(record, stem.with_suffix(".gif"))
    except RuntimeError as error:
        print(f"  {label}: pictures skipped ({error})")
        return []
    return [(f"{label} (PNG)", png), (f"{label} (GIF)", gif)]


if __name__ == "__main__":
    raise SystemExit(main())
