"""`qnav reproduce`: the paper's whole study, run in resumable batches.

Plan: 5 seeds x {recurrent, feedforward} x the four scenarios; then, from the trained runs, the
two cross-dynamics tests and the feedforward agent with 10% random test actions. Runs go to
`runs/study/`, their results to `results/` (one JSON per run, committed), and the tables to
`docs/results.md`. A run whose result exists is skipped, so the study can be stopped and
started again at any point; an interrupted run resumes from its checkpoint.

`qnav sweep` plans one run per point of a settings grid instead. Either plan is run by an
engine: the local runner here (`qnav train` processes, `--jobs` at a time) or Ray
(`training/cluster.py`, docs/cluster.md); the plan, the skip of finished runs, a run's `qnav
train` arguments, its result record and the progress lines are this module's, whichever runs it.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import numpy as np

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import parse_assignments, with_overrides
from qnav.sim import paper
from qnav.training.barn_results import barn_lines

SCENARIOS = ("obstacles-inertia", "walls-inertia", "walls-increment", "obstacles-increment")
MODELS = ("recurrent", "feedforward")
SEEDS = (0, 1, 2, 3, 4)
CROSS = {
    # trained on -> tested on (the paper's generalisation tests, 5 obstacles)
    "obstacles-increment": "obstacles-inertia",
    "obstacles-inertia": "obstacles-increment",
}


@dataclass(frozen=True)
class References:
    """A scenario's reference agents, each as a test result (success, collision, unfinished and
    episodes, as `qnav eval --json` gives them)."""

    random: dict[str, float]
    """A uniformly random action at every step (the paper's Random row)."""
    blind: dict[str, float] | None = None
    """The go-to-target controller, blind to obstacles, on the test layouts."""
    oracle: dict[str, float] | None = None
    """The planner that knows the obstacles' future, on the test layouts (obstacle worlds)."""


@dataclass(frozen=True)
class RunSpec:
    """One training run of the study."""

    scenario: str
    model: str
    seed: int
    relabel: str = "paper"
    ablation: bool = False
    """An ablation run: validated more often, to time when 0.5, 0.8 and 0.9 are first reached."""
    overrides: tuple[str, ...] = ()
    """This run's own settings as SECTION.FIELD=VALUE (a sweep's grid point; train.* are the
    learner's, any other section the world's)."""

    @property
    def name(self) -> str:
        if self.ablation:
            return f"{self.scenario}-{self.model}-seed{self.seed}-ablation-{self.relabel}"
        suffix = "" if self.relabel == "paper" else f"-{self.relabel}"
        point = "".join(f"-{_label(o)}" for o in self.overrides)
        return f"{self.scenario}-{self.model}-seed{self.seed}{suffix}{point}"


def _label(assignment: str) -> str:
    """`train.learning_rate=1e-4` -> `learning_rate=1e-4`, safe as part of a file name."""
    key, value = assignment.split("=", 1)
    text = f"{key.split('.')[-1]}={value}"
    return re.sub(r"[^A-Za-z0-9._=+-]", "_", text)


@dataclass(frozen=True)
class StudySettings:
    """How every run of a study is trained, whichever engine runs it."""

    preset: str = "fast"
    """Learner schedule: fast (ours for 2 CPU cores) or paper."""
    threads: int = 2
    """Torch threads of each run (a Ray task asks for as many CPUs)."""
    common: tuple[str, ...] = ()
    """Settings of every run as SECTION.FIELD=VALUE, applied before a run's own overrides."""

    def __post_init__(self) -> None:
        if self.preset not in ("fast", "paper"):
            raise ConfigError(f"--preset = {self.preset!r}: expected fast or paper")
        if self.threads < 1:
            raise ConfigError(f"--threads = {self.threads}: give at least 1")


def parse_choices(setting: str, text: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
    """A comma-separated list of `allowed` names, in the order given; names the setting if not."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in allowed]
    if not names or unknown:
        raise ConfigError(
            f"{setting} = {text!r}: {'unknown ' + ', '.join(unknown) if unknown else 'empty'}; "
            f"allowed: {', '.join(allowed)}"
        )
    return names


def parse_seeds(text: str, setting: str = "--seeds") -> tuple[int, ...]:
    """A comma-separated list of non-negative seeds; names the setting if not."""
    try:
        seeds = tuple(int(s) for s in text.split(","))
    except ValueError:
        seeds = ()
    if not seeds or min(seeds) < 0:
        raise ConfigError(f"{setting} = {text!r}: expected comma-separated non-negative integers")
    return seeds


def plan(
    scenarios: tuple[str, ...] = SCENARIOS,
    models: tuple[str, ...] = MODELS,
    seeds: tuple[int, ...] = SEEDS,
) -> list[RunSpec]:
    """Every run of the study: walls-only scenarios first (they are the quickest), and within
    them seed by seed, so that a partial study already fills every row of the tables."""
    walls = [s for s in scenarios if not s.startswith("obstacles")]
    obstacles = [s for s in scenarios if s.startswith("obstacles")]
    return [
        RunSpec(s, m, seed)
        for group in (walls, obstacles)
        for seed in seeds
        for s in group
        for m in models
    ]


ABLATION_SCENARIOS = ("walls-increment", "obstacles-inertia")
RELABELS = ("none", "paper", "hindsight")
ABLATION_EPISODES = {"walls-increment": 120, "obstacles-inertia": 600}
"""Training episodes of an ablation run (walls-increment: the study's runs pass 0.99 by 56)."""
ABLATION_EVAL_EVERY_EPISODES = {"walls-increment": 8, "obstacles-inertia": 24}
"""Ablation runs validate after every round of 8 episodes in walls-increment, every third round
in obstacles-inertia (study runs: every 50)."""
ABLATION_LEVELS = ("0.5", "0.8", "0.9")
"""Validation successes whose first reaching the ablation table times (`run.REACHED_LEVELS`)."""


def ablation_plan(seeds: tuple[int, ...] = (0,)) -> list[RunSpec]:
    """Target re-drawing ablation: recurrent agents with each relabel rule."""
    return [
        RunSpec(s, "recurrent", seed, relabel, ablation=True)
        for s in ABLATION_SCENARIOS
        for relabel in RELABELS
        for seed in seeds
    ]


def parse_grid(items: list[str]) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """`["train.learning_rate=1e-4,3e-4", "train.batch_size=32,64"]` -> each setting with its
    values, in the order given; a malformed item names `--grid`."""
    grid: list[tuple[str, tuple[str, ...]]] = []
    for item in items:
        key, equals, text = item.partition("=")
        key = key.strip()
        values = tuple(v.strip() for v in text.split(","))
        if not equals or "." not in key or not all(values):
            raise ConfigError(
                f"--grid {item!r}: expected SECTION.FIELD=VALUE,VALUE,... "
                "(e.g. train.learning_rate=1e-4,3e-4)"
            )
        if key in (k for k, _ in grid):
            raise ConfigError(f"--grid {key} is given twice; list all its values in one --grid")
        grid.append((key, values))
    return tuple(grid)


def grid_points(grid: tuple[tuple[str, tuple[str, ...]], ...]) -> list[tuple[str, ...]]:
    """Every combination of the grid's values, as SECTION.FIELD=VALUE assignments; the last
    setting varies fastest. An empty grid has one point: no change."""
    return [
        tuple(f"{key}={value}" for (key, _), value in zip(grid, values, strict=True))
        for values in itertools.product(*(values for _, values in grid))
    ]


RUN_OPTIONS = {"train.seed": "--seeds", "train.model": "--models", "train.threads": "--threads"}
"""Learner settings a study gives each run through its own options (an assignment would be
overridden by them, silently)."""


def check_assignments(assignments: tuple[str, ...], option: str) -> None:
    """Refuse, by name, a setting that no run could take (an unknown field, a bad value), before
    any run starts: train.* against the learner's settings, anything else the world's."""
    from qnav.sim.config import load_world
    from qnav.training.config import TrainSettings

    for assignment in assignments:
        key = assignment.partition("=")[0].strip()
        if key in RUN_OPTIONS:
            raise ConfigError(
                f"{option} {assignment}: a run's {key} is set by {RUN_OPTIONS[key]} instead"
            )
        nested = parse_assignments([assignment])
        try:
            if "train" in nested:
                with_overrides(TrainSettings(), nested["train"])
            else:
                load_world("walls-inertia", None, [assignment])
        except ConfigError as error:
            raise ConfigError(f"{option} {assignment}: {error}") from None


def sweep_plan(
    scenarios: tuple[str, ...],
    models: tuple[str, ...],
    seeds: tuple[int, ...],
    grid: tuple[tuple[str, tuple[str, ...]], ...],
) -> list[RunSpec]:
    """One run per grid point, scenario, model and seed; grid point by grid point, so that a
    partial sweep has every seed of the first points."""
    return [
        RunSpec(scenario, model, seed, overrides=point)
        for point in grid_points(grid)
        for seed in seeds
        for scenario in scenarios
        for model in models
    ]


def result_path(results_root: Path, spec: RunSpec) -> Path:
    """Where a run's result record lives; its existence means the run is finished."""
    return results_root / f"{spec.name}.json"


def pending(specs: list[RunSpec], results_root: Path) -> list[RunSpec]:
    """The runs still to do, in plan order: a run with a result is skipped (and an unfinished
    one resumes from its run folder's checkpoint when started again)."""
    return [s for s in specs if not result_path(results_root, s).exists()]


def train_argv(spec: RunSpec, run_dir: Path, study: StudySettings) -> list[str]:
    """The `qnav train` arguments of one run: every engine trains a run with exactly these."""
    options = [
        "--scenario", spec.scenario, "--model", spec.model, "--seed", str(spec.seed),
        "--preset", study.preset, "--run-dir", str(run_dir),
        "--train-set", f"train.threads={study.threads}",
    ]  # fmt: skip
    if spec.relabel != "paper":  # both presets' own rule, which a sweep may vary (train.relabel)
        options += ["--relabel", spec.relabel]
    for assignment in (*study.common, *spec.overrides):
        options += ["--train-set" if assignment.startswith("train.") else "--set", assignment]
    if spec.ablation:
        options += [
            "--episodes", str(ABLATION_EPISODES[spec.scenario]),
            "--train-set",
            f"train.eval_every_episodes={ABLATION_EVAL_EVERY_EPISODES[spec.scenario]}",
        ]  # fmt: skip
    return ["train", "--quiet", *options]


Command = Callable[[list[str]], int]
"""The `qnav` command line run in this process (`qnav.cli.main`), handed in by the shell:
training imports nothing of the shell."""


def execute(spec: RunSpec, run_dir: Path, study: StudySettings, command: Command) -> dict[str, Any]:
    """Train (or resume) one run in this process and return its result record: what a Ray
    task does (the local runner starts the same `qnav train` as a process of its own)."""
    code = command(train_argv(spec, run_dir, study))
    if code != 0:
        raise RuntimeError(f"qnav train of {spec.name} exited {code}")
    return record(spec, run_dir)


def _eval_json(run_dir: Path, extra: list[str]) -> dict[str, Any]:
    output = subprocess.run(
        [sys.executable, "-m", "qnav", "eval", "--policy", str(run_dir), "--json", *extra],
        capture_output=True,
        text=True,
        check=True,
    )
    return dict(json.loads(output.stdout))


def record(spec: RunSpec, run_dir: Path) -> dict[str, Any]:
    """A finished run's result record: its results.json with the study's extra tests of it."""
    results: dict[str, Any] = json.loads((run_dir / "results.json").read_text())
    extra: dict[str, Any] = {"ablation": True} if spec.ablation else {}
    if spec.overrides:
        extra["overrides"] = list(spec.overrides)
    if spec.scenario in CROSS:
        extra["cross_dynamics"] = {
            "tested_on": CROSS[spec.scenario],
            "test": _eval_json(run_dir, ["--scenario", CROSS[spec.scenario]]),
        }
    if spec.model == "feedforward" and spec.scenario == "walls-increment":
        extra["random_actions_10pct"] = _eval_json(run_dir, ["--random-action-prob", "0.1"])
    return results | extra


def write_result(results_root: Path, spec: RunSpec, result: dict[str, Any]) -> Path:
    """Store a run's record (written whole, then renamed: a half-written one never counts)."""
    path = result_path(results_root, spec)
    partial = path.with_suffix(".json.partial")
    partial.write_text(json.dumps(result, indent=2) + "\n")
    partial.replace(path)
    return path


def skipped_lines(
    specs: list[RunSpec], run_root: Path, results_root: Path, *, trained: bool = True
) -> list[str]:
    """What `qnav reproduce` took as it was instead of making it again, and how to make it again:
    a run with a result is not trained (its network, in `run_root`, is not committed: a fresh
    clone has none), a run without one is not trained with `trained` False (`--tables-only`),
    and the rows beyond the paper are read from their results, never re-evaluated."""
    kept = [s for s in specs if result_path(results_root, s).exists()]
    lines = []
    if kept:
        lines.append(
            f"skipping {len(kept)} of {len(specs)} runs: each has its result in {results_root}/, "
            "so it is not trained again"
        )
        if not any((run_root / s.name / "model.pt").exists() for s in kept):
            lines.append(
                f"  none of their networks is in {run_root}/ (run folders are not committed; a "
                f"fresh clone has none): the tables come from {results_root}/ as it is"
            )
        lines.append(
            f"  to train a run again: delete its {results_root}/NAME.json and run `qnav "
            f"reproduce` again (it trains in {run_root}/NAME); --results-dir EMPTY_FOLDER "
            "trains them all"
        )
    missing = len(specs) - len(kept)
    if missing and not trained:
        lines.append(
            f"skipping {missing} runs without a result (--tables-only): `qnav reproduce` "
            "without it trains them"
        )
    for method in BEYOND_THE_PAPER:
        count = len(list((results_root / method.folder).glob("*.json")))
        if count:
            lines.append(
                f"not re-evaluating the {count} {method.folder} results in "
                f"{results_root / method.folder}/; each is made by `{method.command}`"
            )
    return lines


def run_progress(run_dir: Path) -> tuple[int, int] | None:
    """(episodes done, episodes planned) of a run folder, or None before its first round."""
    try:
        planned = int(tomllib.loads((run_dir / "settings.toml").read_text())["train"]["episodes"])
        rows = (run_dir / "progress.csv").read_text().splitlines()
    except (OSError, KeyError, ValueError, tomllib.TOMLDecodeError):
        return None
    if len(rows) < 2:
        return None
    done = dict(zip(rows[0].split(","), rows[-1].split(","), strict=False)).get("episodes", "0")
    return int(float(done or 0)), planned


Outcome = tuple[RunSpec, dict[str, Any] | str]
"""A run that ended: its result record, or why it failed."""


class Engine(Protocol):
    """What runs a study's trainings: the local runner below, or Ray (training/cluster.py)."""

    def capacity(self) -> int:
        """How many runs may be in flight now."""
        ...

    def start(self, spec: RunSpec) -> None:
        """Start (or resume) one run."""
        ...

    def ended(self) -> list[Outcome]:
        """The runs that ended since the last call (without waiting)."""
        ...

    def run_dir(self, spec: RunSpec) -> Path:
        """Where the driver sees the run's folder (for progress and, when done, its files)."""
        ...

    def close(self) -> None:
        """Let go of what the engine holds (runs still going are not waited for)."""
        ...


@dataclass
class LocalRunner:
    """Each run a `qnav train` process on this machine, `jobs` at a time."""

    run_root: Path
    study: StudySettings
    jobs: int = 1
    running: dict[RunSpec, subprocess.Popen[bytes]] = field(default_factory=dict)

    def capacity(self) -> int:
        return self.jobs

    def run_dir(self, spec: RunSpec) -> Path:
        return self.run_root / spec.name

    def start(self, spec: RunSpec) -> None:
        argv = train_argv(spec, self.run_dir(spec), self.study)
        self.running[spec] = subprocess.Popen([sys.executable, "-m", "qnav", *argv])

    def ended(self) -> list[Outcome]:
        ended: list[Outcome] = []
        for spec, process in list(self.running.items()):
            if process.poll() is None:
                continue
            del self.running[spec]
            if process.returncode != 0:
                ended.append((spec, f"exit {process.returncode}"))
            else:
                ended.append((spec, record(spec, self.run_dir(spec))))
        return ended

    def close(self) -> None:
        for process in self.running.values():
            process.terminate()  # it resumes from its checkpoint next time


def run_study(
    specs: list[RunSpec],
    run_root: Path,
    *,
    results_root: Path,
    jobs: int = 1,
    threads: int | None = None,
    preset: str = "fast",
    time_budget_s: float | None = None,
    common: tuple[str, ...] = (),
    engine: Callable[[StudySettings], Engine] | None = None,
    poll_s: float = 1.0,
) -> list[RunSpec]:
    """Train every spec without a result, on `engine` (default: the local runner, `jobs` at a
    time with `threads` torch threads each, by default the cores shared among the jobs);
    returns those finished now."""
    if jobs < 1:
        raise ConfigError(f"--jobs = {jobs}: give at least 1")
    if threads is not None and threads < 1:
        raise ConfigError(f"--threads = {threads}: give at least 1")
    study = StudySettings(preset, threads or max(1, (os.cpu_count() or 2) // jobs), common)
    check_assignments(study.common, "--set")
    for spec in specs:
        check_assignments(spec.overrides, "--grid")
    todo = pending(specs, results_root)
    print(f"{len(specs) - len(todo)} of {len(specs)} runs already have results", flush=True)
    if not todo:
        return []
    results_root.mkdir(parents=True, exist_ok=True)
    runner = engine(study) if engine else LocalRunner(run_root, study, jobs)
    try:
        started = time.monotonic()
        running: list[RunSpec] = []
        finished: list[RunSpec] = []
        failed = 0
        shown: dict[RunSpec, tuple[int, int] | None] = {}
        while todo or running:
            out_of_time = time_budget_s is not None and time.monotonic() - started > time_budget_s
            while todo and len(running) < runner.capacity() and not out_of_time:
                spec = todo.pop(0)
                print(f"start  {spec.name}", flush=True)
                runner.start(spec)
                running.append(spec)
            for spec, outcome in runner.ended():
                running.remove(spec)
                if isinstance(outcome, str):
                    failed += 1
                    print(f"FAILED {spec.name} ({outcome})", flush=True)
                    continue
                write_result(results_root, spec, outcome)
                finished.append(spec)
                done = len(specs) - len(pending(specs, results_root))
                print(f"done   {spec.name} ({done} of {len(specs)} runs done)", flush=True)
            for spec in running:
                now = run_progress(runner.run_dir(spec))
                if now is not None and now != shown.get(spec):
                    shown[spec] = now
                    print(f"       {spec.name}: {now[0]} of {now[1]} episodes", flush=True)
            if out_of_time and not running:
                print(f"time budget spent; {len(todo)} runs left for the next batch")
                break
            if todo or running:
                time.sleep(poll_s)
    finally:
        runner.close()
    done = len(specs) - len(pending(specs, results_root))
    print(f"study: {done} of {len(specs)} runs have results ({failed} failed now)", flush=True)
    return finished


def sweep_table(specs: list[RunSpec], results_root: Path) -> str:
    """A sweep's runs as a Markdown table: settings, seed, test figures (or 'not run yet')."""
    lines = [
        _row("scenario", "model", "settings", "seed", "success", "collision", "unfinished"),
        _row(*["---"] * 7),
    ]
    for spec in specs:
        path = result_path(results_root, spec)
        point = ", ".join(spec.overrides) or "-"
        if not path.exists():
            lines.append(_row(spec.scenario, spec.model, point, spec.seed, "not run yet", "", ""))
            continue
        test = json.loads(path.read_text())["test"]
        figures = (f"{test[k]:.3f}" for k in ("success", "collision", "unfinished"))
        lines.append(_row(spec.scenario, spec.model, point, spec.seed, *figures))
    return "\n".join(lines)


def _load(results_root: Path) -> dict[str, dict[str, Any]]:
    return {p.stem: json.loads(p.read_text()) for p in sorted(results_root.glob("*.json"))}


class BeyondThePaper(NamedTuple):
    """A method beyond the paper's, measured on each obstacle study run's DQN: its rows and
    goal lines in docs/results.md come from `results/{folder}/SCENARIO-MODEL-seedK.json`
    (`command`: `qnav eval --json` of that run with the look ahead)."""

    folder: str
    """Under the results folder; also the row's name ("Recurrent, {folder}")."""
    lookahead: str
    """`qnav eval`'s look ahead options that make one result."""
    what: str
    """What the row measures, a sentence for the results page."""

    @property
    def command(self) -> str:
        """How one result is made."""
        return (
            f"qnav eval --policy RUN {self.lookahead} --episodes 1000 --json > "
            f"results/{self.folder}/SCENARIO-MODEL-seedK.json"
        )


BEYOND_THE_PAPER = (
    BeyondThePaper(
        "shielded",
        "--lookahead shield",
        "each run's DQN shielded by the controller's look ahead: its greedy action unless at "
        "least 0.3 of the continuations after it collide in the forecast (the onboard tracker's "
        "obstacles, moving straight on for 6 s), then its best-valued among those colliding "
        "least, over the test protocol's layouts (the policy learned, the forecast not; "
        "docs/controller.md, 'Moving obstacles: the look ahead')",
    ),
)
"""The rows beyond the paper's method, in the order the tables show them."""


Beyond = dict[tuple[str, str, str], list[dict[str, float]]]
"""Tests of the methods beyond the paper's by (method folder, model, scenario): `beyond_tests`."""


def beyond_tests(
    results_root: Path, scenario: str, method: BeyondThePaper, model: str = "recurrent"
) -> list[dict[str, float]]:
    """A method beyond the paper's on one model's study runs: its test results in a scenario,
    one per seed."""
    folder = results_root / method.folder
    return [
        json.loads(path.read_text())
        for path in sorted(folder.glob(f"{scenario}-{model}-seed*.json"))
    ]


def _cells(tests: list[dict[str, float]]) -> list[str]:
    """'mean +- std' of success, collision and unfinished over runs."""
    cells = []
    for key in ("success", "collision", "unfinished"):
        values = np.array([t[key] for t in tests])
        cells.append(f"{values.mean():.3f} +- {values.std():.3f}")
    return cells


def _row(*cells: object) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _paper_cell(mean: paper.Fractions, std: paper.Fractions) -> str:
    return " / ".join(f"{m} +- {s}" for m, s in zip(mean, std, strict=True))


def _runs(
    results: dict[str, dict[str, Any]],
    scenario: str,
    model: str,
    relabel: str = "paper",
    ablation: bool = False,
) -> list[dict[str, Any]]:
    wanted = (scenario, model, relabel, ablation)
    return [
        r
        for r in results.values()
        if (r["scenario"], r["model"], r.get("relabel", "paper"), r.get("ablation", False))
        == wanted
    ]


def _study_runs(results: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The runs of the study proper (the paper's re-drawing, not an ablation)."""
    return [
        r
        for r in results.values()
        if r.get("relabel", "paper") == "paper" and not r.get("ablation")
    ]


def _ablation_row(scenario: str, relabel: str, runs: list[dict[str, Any]]) -> str:
    if not runs:
        return _row(scenario, relabel, 0, "not run yet", *[""] * (2 * len(ABLATION_LEVELS) + 1))
    cells = []
    for level in ABLATION_LEVELS:
        reached = [r.get("first_reached", {}).get(level) for r in runs]
        cells.append(", ".join(f"{int(r['episodes'])}" if r else "-" for r in reached))
        cells.append(", ".join(f"{r['wall_s'] / 60:.1f}" if r else "-" for r in reached))
    success = np.mean([r["test"]["success"] for r in runs])
    return _row(scenario, relabel, len(runs), *cells, f"{success:.3f}")


SUCCESS_GOALS = {
    # scenario -> the goal for the recurrent agent's mean test success over 5 seeds
    "obstacles-inertia": 0.90,
    "walls-inertia": 1.0,
    "walls-increment": 0.995,
    "obstacles-increment": 0.80,
}
RECURRENT_MARGIN = {"obstacles-inertia": 0.1, "obstacles-increment": 0.1}
"""How much the recurrent agent's mean success must exceed the feedforward one's, by scenario
(issue 19; the paper: +0.41 and +0.44); elsewhere it must only be higher."""
HEADROOM_GOAL = 0.8
"""Share of the room above the blind controller, (success - blind) / (oracle - blind), the
recurrent agent must take in each obstacle scenario."""
WALLS_LEARNED_WITHIN_EPISODES = 200
"""Walls-only worlds must reach 0.99 validation success within this many training episodes."""
MINUTES_PER_RUN_LIMIT = {"walls": 10.0, "obstacles": 30.0}
"""Wall-time limit of one training run on 2 CPU cores, by kind of world."""


def _minutes(run: dict[str, Any]) -> float:
    return float(run["collect_s"] + run["train_s"] + run["eval_s"]) / 60


def _minutes_limit(scenario: str) -> float:
    return MINUTES_PER_RUN_LIMIT["obstacles" if scenario.startswith("obstacles") else "walls"]


def _verdict(met: bool) -> str:
    return "met" if met else "**not met**"


def _mean_success(runs: list[dict[str, Any]]) -> float:
    return float(np.mean([r["test"]["success"] for r in runs]))


def _beats_row(label: str, recurrent: list[float], feedforward: list[float], margin: float) -> str:
    """A "recurrent beats feedforward" goal row from each model's test successes: by at least
    `margin`, or by anything where it is 0."""
    ours = float(np.mean(recurrent)), float(np.mean(feedforward))
    met = ours[0] - ours[1] >= margin if margin else ours[0] > ours[1]
    return _row(label, f"{ours[0]:.3f} vs {ours[1]:.3f}", f"{len(recurrent)} + {len(feedforward)}",
                _verdict(met) if ours[0] < 1 else "met (recurrent 1.0)")  # fmt: skip


def headroom_taken(success: float, blind: float, oracle: float) -> float:
    """Share of the room the world leaves above the blind controller that `success` takes:
    (success - blind) / (oracle - blind); 0 at the blind controller's level, 1 at the oracle's."""
    if oracle <= blind:
        raise ValueError(f"no room above the blind controller: oracle {oracle} <= blind {blind}")
    return (success - blind) / (oracle - blind)


def _goal_lines(
    results: dict[str, dict[str, Any]],
    references: dict[str, References],
    beyond: Beyond,
) -> list[str]:
    """The issues' goals, each with what the finished runs reach (and the methods beyond the
    paper's)."""
    return [
        "## Goals",
        "",
        "Each goal against the runs finished so far (a goal over 5 seeds is provisional until",
        "n = 5).",
        "",
        _row("goal", "ours", "n", "verdict"),
        _row(*["---"] * 4),
        *_success_goal_rows(results),
        *_margin_goal_rows(results),
        *_headroom_goal_rows(results, references),
        *_beyond_goal_rows(references, beyond),
        *_compute_goal_rows(results),
        "",
    ]


def _success_goal_rows(results: dict[str, dict[str, Any]]) -> list[str]:
    """Each table's recurrent success against its goal."""
    rows = []
    for scenario, goal in SUCCESS_GOALS.items():
        runs = _runs(results, scenario, "recurrent")
        label = f"Table {paper.TABLES[scenario]} ({scenario}) recurrent success >= {goal:g}"
        if not runs:
            rows.append(_row(label, "not run yet", 0, ""))
            continue
        mean = _mean_success(runs)
        rows.append(_row(label, f"{mean:.3f}", len(runs), _verdict(mean >= goal)))
    return rows


def _margin_goal_rows(results: dict[str, dict[str, Any]]) -> list[str]:
    """Each table's recurrent runs against its feedforward ones (by its margin, where asked)."""
    rows = []
    for scenario in SCENARIOS:
        recurrent, feedforward = (_runs(results, scenario, m) for m in MODELS)
        margin = RECURRENT_MARGIN.get(scenario, 0.0)
        label = f"Table {paper.TABLES[scenario]}: recurrent beats feedforward" + (
            f" by >= {margin:g}" if margin else ""
        )
        if not recurrent or not feedforward:
            rows.append(_row(label, "not run yet", f"{len(recurrent)} + {len(feedforward)}", ""))
            continue
        rows.append(
            _beats_row(
                label,
                [r["test"]["success"] for r in recurrent],
                [r["test"]["success"] for r in feedforward],
                margin,
            )
        )
    return rows


def _headroom_goal_rows(
    results: dict[str, dict[str, Any]], references: dict[str, References]
) -> list[str]:
    """Each obstacle table's share of the headroom the recurrent runs take."""
    rows = []
    for scenario in (s for s in SCENARIOS if s.startswith("obstacles")):
        runs = _runs(results, scenario, "recurrent")
        bounds = references.get(scenario)
        label = (
            f"Table {paper.TABLES[scenario]}: recurrent takes >= {HEADROOM_GOAL:g} of the "
            "headroom, (success - blind) / (oracle - blind)"
        )
        if not runs or bounds is None or bounds.blind is None or bounds.oracle is None:
            rows.append(_row(label, "not run yet", len(runs), ""))
            continue
        blind, oracle = bounds.blind["success"], bounds.oracle["success"]
        taken = headroom_taken(_mean_success(runs), blind, oracle)
        rows.append(
            _row(label, f"{taken:.2f} (blind {blind:.3f}, oracle {oracle:.3f})", len(runs),
                 _verdict(taken >= HEADROOM_GOAL))
        )  # fmt: skip
    return rows


def _beyond_goal_rows(references: dict[str, References], beyond: Beyond) -> list[str]:
    """The methods beyond the paper's: recurrent against feedforward, and against the paper's
    figure and the headroom."""
    rows = []
    for (method, model, scenario), tests in beyond.items():
        if model != "recurrent":
            continue
        feedforward = beyond[method, "feedforward", scenario]
        margin = RECURRENT_MARGIN.get(scenario, 0.0)
        if tests and feedforward and margin:
            rows.append(
                _beats_row(f"Table {paper.TABLES[scenario]}, beyond the paper: recurrent {method} "
                           f"beats feedforward {method} by >= {margin:g}",
                           [t["success"] for t in tests], [t["success"] for t in feedforward],
                           margin)
            )  # fmt: skip
        bounds = references.get(scenario)
        if not tests or bounds is None or bounds.blind is None or bounds.oracle is None:
            continue
        goal = paper.RECURRENT[scenario][0][0]
        mean = float(np.mean([t["success"] for t in tests]))
        taken = headroom_taken(mean, bounds.blind["success"], bounds.oracle["success"])
        rows.append(
            _row(f"Table {paper.TABLES[scenario]}, beyond the paper: recurrent {method} reaches "
                 f"the paper's {goal:g} and >= {HEADROOM_GOAL:g} of the headroom",
                 f"{mean:.3f}, headroom {taken:.2f}", len(tests),
                 _verdict(mean >= goal and taken >= HEADROOM_GOAL))
        )  # fmt: skip
    return rows


def _compute_goal_rows(results: dict[str, dict[str, Any]]) -> list[str]:
    """How quickly the walls-only runs learn, and how long runs take against their limits."""
    rows = []
    walls = [
        r
        for s in SCENARIOS
        if not s.startswith("obstacles")
        for r in _runs(results, s, "recurrent")
    ]
    if walls:
        reached = [(r.get("first_reached", {}).get("0.99") or {}).get("episodes") for r in walls]
        within = sum(e is not None and e <= WALLS_LEARNED_WITHIN_EPISODES for e in reached)
        rows.append(
            _row(f"walls-only, recurrent: 0.99 validation success within "
                 f"{WALLS_LEARNED_WITHIN_EPISODES} episodes", f"{within} of {len(walls)} runs",
                 len(walls), _verdict(within == len(walls)))
        )  # fmt: skip
    for kind, limit in MINUTES_PER_RUN_LIMIT.items():
        runs = [r for r in _study_runs(results) if r["scenario"].startswith(kind)]
        if runs:
            inside = sum(_minutes(r) <= limit for r in runs)
            rows.append(
                _row(f"{kind} runs take at most {limit:g} minutes", f"{inside} of {len(runs)} "
                     f"runs (longest {max(map(_minutes, runs)):.1f})", len(runs),
                     _verdict(inside == len(runs)))
            )  # fmt: skip
    return rows


def _reference_rows(scenario: str, bounds: References | None) -> list[str]:
    """The reference agents' rows of a scenario's table (none measured: none shown)."""
    if bounds is None:
        return []
    rows = []
    for agent, result, quoted in (
        ("Random", bounds.random, " / ".join(str(v) for v in paper.RANDOM[scenario])),
        ("Go-to-target (blind)", bounds.blind, ""),
        ("Oracle planner", bounds.oracle, ""),
    ):
        if result is not None:
            rows.append(
                _row(agent, f"{int(result['episodes'])} episodes",
                     *(f"{result[k]:.3f}" for k in ("success", "collision", "unfinished")), quoted)
            )  # fmt: skip
    return rows


def _beyond_lines(scenario: str, beyond: Beyond) -> list[str]:
    """What each row beyond the paper in a scenario's table is, where there is one."""
    lines = []
    for method in BEYOND_THE_PAPER:
        if any(beyond[method.folder, model, scenario] for model in MODELS):
            lines += [
                "",
                f"{method.folder.capitalize()}: {method.what}. Each result: `{method.command}`.",
            ]
    return lines


def _gauge_line(results: dict[str, dict[str, Any]], scenario: str) -> list[str]:
    """The decisive-state gauge of the shipped networks, per model (runs that recorded it: the
    gauge was retired after commit 7d4f731, and the committed results keep its scores)."""
    cells = []
    for model in MODELS:
        judged = [r["decisive"] for r in _runs(results, scenario, model) if r.get("decisive")]
        if judged:
            safe, balanced = (np.mean([j[k] for j in judged]) for k in ("safe", "balanced"))
            cells.append(f"{model} {safe:.3f} / {balanced:.3f} (n = {len(judged)})")
    if not cells:
        return []
    return [
        "",
        "Decisive-state gauge of the shipped networks (docs/learner.md): the share of decisive "
        "states where the greedy action is safe / that share balanced over the doom patterns, "
        "0.5 for any choice blind to the scan: " + "; ".join(cells) + ".",
    ]


def results_markdown(results_root: Path, references: dict[str, References]) -> str:
    """docs/results.md: our tables beside the paper's."""
    results = _load(results_root)
    beyond = {
        (method.folder, model, scenario): beyond_tests(results_root, scenario, method, model)
        for method in BEYOND_THE_PAPER
        for model in MODELS
        for scenario in SCENARIOS
    }
    lines = [*_intro_lines(results), *_goal_lines(results, references, beyond)]
    for scenario in SCENARIOS:
        lines += _table_lines(scenario, results, references.get(scenario), beyond)
    lines += _generalisation_lines(results)
    lines += _ablation_lines(results)
    lines += _compute_lines(results)
    lines += barn_lines(results_root)
    return "\n".join(lines) + "\n"


_HEADER = _row("agent", "n", "success", "collision", "unfinished", "paper s / c / u")
_RULE = _row(*["---"] * 6)


def _intro_lines(results: dict[str, dict[str, Any]]) -> list[str]:
    """The results page's title, how it is made, and the study's status."""
    return [
        "# Results: the paper's tables, reproduced",
        "",
        "Generated by `qnav reproduce` from `results/*.json` (one file per training run). Each",
        "figure is the mean +- std over the seeds that have finished (n), under the paper's test",
        "protocol: greedy policy, 200 episodes of up to 500 steps. Paper values beside ours. The",
        "reference agents: Random over 1000 episodes; the blind go-to-target controller and the",
        "oracle planner that knows the obstacles' future (`lab.oracle`) on the agents' own 200",
        "test layouts.",
        "",
        f"Status: {len(_study_runs(results))} of "
        f"{len(plan())} study runs finished. Known gap: moving obstacles. The world was "
        "re-pinned on 2026-12-03 to every number the paper gives (docs/simulator.md; the "
        "obstacle radius went from 0.4 to 0.2 m), so the obstacle runs of the world before "
        "it left these tables for results/world-before-2026-12-03/ (there even the oracle "
        "planner reached only 0.78 in obstacles-inertia) and run again. In the new world the "
        "paper's method stops near the blind go-to-target controller's level (the Go-to-target "
        "rows; docs/learner.md, 'The re-pinned obstacle world').",
        "",
    ]


def _table_lines(
    scenario: str,
    results: dict[str, dict[str, Any]],
    bounds: References | None,
    beyond: Beyond,
) -> list[str]:
    """One of the paper's tables: the reference agents, each model's runs and its best, the
    methods beyond the paper's, the gauge."""
    lines = [f"## Table {paper.TABLES[scenario]}: {scenario}", "", _HEADER, _RULE]
    lines += _reference_rows(scenario, bounds)
    for model, reference in (("feedforward", paper.FEEDFORWARD), ("recurrent", paper.RECURRENT)):
        runs = _runs(results, scenario, model)
        quoted = _paper_cell(*reference[scenario])
        if not runs:
            lines.append(_row(model.capitalize(), 0, "not run yet", "", "", quoted))
            continue
        tests = [r["test"] for r in runs]
        best = max(tests, key=lambda t: t["success"])
        lines.append(_row(model.capitalize(), len(runs), *_cells(tests), quoted))
        lines.append(
            _row(
                f"{model.capitalize()} (best)",
                "",
                *(f"{best[k]:.3f}" for k in ("success", "collision", "unfinished")),
                "",
            )
        )
    for method, model in itertools.product(BEYOND_THE_PAPER, reversed(MODELS)):
        tests = beyond[method.folder, model, scenario]
        if tests:
            lines.append(
                _row(f"{model.capitalize()}, {method.folder} (beyond the paper; "
                     f"{int(tests[0]['episodes'])} episodes)", len(tests), *_cells(tests), "")
            )  # fmt: skip
    return [*lines, *_gauge_line(results, scenario), *_beyond_lines(scenario, beyond), ""]


def _generalisation_lines(results: dict[str, dict[str, Any]]) -> list[str]:
    """The cross-dynamics tests and the random test actions, beside the paper's."""
    lines = [
        "## Generalisation and random test actions",
        "",
        _HEADER.replace("agent", "test"),
        _RULE,
    ]
    extra_tests = [
        ((trained, "recurrent"), "cross_dynamics", f"recurrent, trained on {trained}, tested on "
         f"{tested}", _paper_cell(*paper.CROSS_DYNAMICS[trained, tested]))
        for trained, tested in CROSS.items()
    ] + [
        (("walls-increment", "feedforward"), "random_actions_10pct",
         "feedforward, walls-increment, 10% random test actions",
         _paper_cell(*paper.FEEDFORWARD_RANDOM_ACTIONS)),
    ]  # fmt: skip
    for (scenario, model), key, label, quoted in extra_tests:
        tests = [r[key].get("test", r[key]) for r in _runs(results, scenario, model) if key in r]
        if tests:
            lines.append(_row(label, len(tests), *_cells(tests), quoted))
        else:
            lines.append(_row(label, 0, "not run yet", "", "", quoted))
    return lines


def _ablation_lines(results: dict[str, dict[str, Any]]) -> list[str]:
    """The target re-drawing ablation: each rule's runs, how soon they reach each level."""
    lines = [
        "",
        "## Target re-drawing ablation",
        "",
        "Recurrent agents, one run per seed (n; `qnav reproduce --ablation --ablation-seeds`)",
        "with each rule, trained for",
        ", ".join(f"{n} episodes ({s})" for s, n in ABLATION_EPISODES.items()) + "; validation",
        "success (greedy, 100 episodes of up to 200 steps) every "
        + ", ".join(f"{n} episodes ({s})" for s, n in ABLATION_EVAL_EVERY_EPISODES.items())
        + ". Figures per run, in seed order; test success is the mean. '-' = never reached "
        "within the run. The obstacles-inertia rows were rerun in the re-pinned world "
        "(2026-12-04; every ablation run again on 2026-12-06, to time 0.8 too), where the blind "
        "go-to-target controller scores 0.671 (`qnav eval --scenario obstacles-inertia --agent "
        "goto --episodes 1000`).",
        "",
        _row(
            "scenario",
            "re-drawing",
            "n",
            *(
                f"{what} to {level}"
                for level in ABLATION_LEVELS
                for what in ("episodes", "minutes")
            ),
            "test success",
        ),
        _row(*["---"] * (4 + 2 * len(ABLATION_LEVELS))),
    ]
    for scenario in ABLATION_SCENARIOS:
        for relabel in RELABELS:
            runs = _runs(results, scenario, "recurrent", relabel, ablation=True)
            lines.append(_ablation_row(scenario, relabel, runs))
    return lines


def _compute_lines(results: dict[str, dict[str, Any]]) -> list[str]:
    """Each scenario's and model's wall time per run, and how soon it first reached 0.99."""
    lines = [
        "",
        "## Compute",
        "",
        "Wall time of each run (collection, training, evaluations) on this project's 2-core",
        "machine; runs that shared the cores with other jobs are slower. Validation success is",
        "checked after every round of 8 episodes that crosses a multiple of 50.",
        "",
        _row("scenario", "model", "n", "minutes per run (median, max)", "limit",
             "first 0.99 validation (episodes, per run)", "iterations"),
        _row(*["---"] * 7),
    ]  # fmt: skip
    for scenario in SCENARIOS:
        for model in MODELS:
            runs = sorted(_runs(results, scenario, model), key=lambda r: int(r["seed"]))
            if runs:
                minutes = [_minutes(r) for r in runs]
                first = [
                    (r.get("first_reached", {}).get("0.99") or {}).get("episodes") for r in runs
                ]
                lines.append(
                    _row(scenario, model, len(runs),
                         f"{np.median(minutes):.1f}, {max(minutes):.1f}",
                         f"{_minutes_limit(scenario):g}",
                         ", ".join("-" if e is None else str(int(e)) for e in first),
                         runs[0]["iterations"])
                )  # fmt: skip
    return lines
