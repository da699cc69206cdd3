"""Handlers of the learning verbs: train, export, reproduce, sweep, figures."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from qnav.contracts.errors import ConfigError
from qnav.contracts.policy_file import WEIGHT_TYPES
from qnav.contracts.settings import load_toml, with_overrides
from qnav.options import add_print_config, config_text, settings_from_args
from qnav.sim.config import WorldConfig, load_world
from qnav.sim.evaluate import EvalSettings, GoToTargetAgent, RandomAgent
from qnav.sim.evaluate import evaluate as run_evaluation
from qnav.training.config import PRESETS
from qnav.verbs.parser import Parser, Verbs, flag, repeated, settings_options, verb, world_options

if TYPE_CHECKING:
    from qnav.training.study import Engine, References, RunSpec, StudySettings


def train(args: argparse.Namespace) -> int:
    """Train (or resume) one run."""
    from qnav.training.config import preset
    from qnav.training.run import train as run_training

    world: WorldConfig = load_world(args.scenario, args.world_config, args.assignments)
    settings = preset(args.preset, world)
    if args.train_config is not None:
        settings = with_overrides(settings, load_toml(args.train_config).get("train", {}))
    settings = settings_from_args(settings, args, assignments=args.train_assignments)
    if args.print_config:
        print(config_text(settings), end="")
        return 0
    run_dir = args.run_dir or Path("runs") / world.name / (
        f"{settings.model}-seed{settings.seed}-{args.preset}"
        + ("" if settings.relabel == "paper" else f"-{settings.relabel}")
    )
    print(f"run folder: {run_dir}")
    results = run_training(world, settings, run_dir, progress=not args.quiet)
    test = results["test"]
    print(
        f"test ({test['episodes']} episodes of up to 500 steps): success {test['success']:.3f}, "
        f"collision {test['collision']:.3f}, unfinished {test['unfinished']:.3f}"
    )
    print(f"wrote {run_dir}/results.json, progress.csv, success.png, model.pt")
    return 0


def export(args: argparse.Namespace) -> int:
    """A run's network as one ONNX policy file, tested and stamped with its results."""
    from qnav.training.export import AGREEMENT_KEY, export_run, reexport_file

    default_episodes = 200 if args.run.suffix != ".onnx" or args.weights else 0
    episodes = default_episodes if args.eval_episodes is None else args.eval_episodes
    if args.run.suffix == ".onnx":
        if args.output is None:
            raise ConfigError("re-exporting a policy file needs -o FILE.onnx (it may be the same)")
        output = args.output
        contract = reexport_file(
            args.run,
            output,
            eval_episodes=episodes,
            weight_type=args.weights,
            progress=not args.quiet,
            turn_commitment=args.turn_commitment,
        )
    else:
        output = args.output or args.run / "policy.onnx"
        contract = export_run(
            args.run,
            output,
            eval_episodes=episodes,
            weight_type=args.weights or "float32",
            progress=not args.quiet,
            turn_commitment=args.turn_commitment,
        )
    print(
        f"wrote {output} ({output.stat().st_size / 1e6:.1f} MB, {contract.weight_type} weights "
        "inside)"
    )
    print(
        f"  {contract.model_kind}, {contract.scenario}, window {contract.window_length}, "
        f"{contract.num_beams} beams, period {contract.control_period_s} s"
        + (", turn commitment" if contract.turn_commitment else "")
    )
    if contract.evaluation:
        e = contract.evaluation
        print(
            f"  this file under the test protocol ({int(e['episodes'])} episodes): success "
            f"{e['success']:.3f}, collision {e['collision']:.3f}, unfinished {e['unfinished']:.3f}"
        )
        if AGREEMENT_KEY in e:
            print(f"  its decisions agree with the float32 network's in {e[AGREEMENT_KEY]:.2%}")
    return 0


def reproduce(args: argparse.Namespace) -> int:
    """Run the study's missing runs, then write docs/results.md."""
    from qnav.sim import paper
    from qnav.sim.config import scenario
    from qnav.training.study import (
        ablation_plan,
        parse_seeds,
        plan,
        results_markdown,
        skipped_lines,
    )

    scenarios, models, seeds = _study_axes(args)
    specs = plan(scenarios, models, seeds)
    if args.ablation:
        ablation_seeds = parse_seeds(args.ablation_seeds, "--ablation-seeds")
        specs += [s for s in ablation_plan(ablation_seeds) if s.scenario in scenarios]
    for line in skipped_lines(specs, args.runs_dir, args.results_dir, trained=not args.tables_only):
        print(line, flush=True)
    if not args.tables_only:
        _run_study(args, specs)
    print("testing the reference agents (Random, go-to-target, the oracle planner) ...", flush=True)
    references = {name: _references(scenario(name)) for name in paper.RANDOM}
    args.docs.parent.mkdir(parents=True, exist_ok=True)
    args.docs.write_text(results_markdown(args.results_dir, references))
    print(f"wrote {args.docs}: the tables from {args.results_dir}/")
    return 0


def _references(world: WorldConfig) -> References:
    """The reference agents of a scenario's table: Random over 1000 episodes; the blind
    go-to-target controller and, where obstacles move, the oracle planner on the test layouts
    (the agents' own, so each agent is compared layout for layout)."""
    from qnav.lab.oracle import run_oracle
    from qnav.training.study import References

    random = run_evaluation(
        world, RandomAgent(250, seed=1), EvalSettings(episodes=1000, num_worlds=250), progress=False
    )
    test = EvalSettings()
    blind = run_evaluation(world, GoToTargetAgent(), test, progress=False)
    # The planner is slow: 50 worlds at a time keep its batches small (same layouts).
    oracle = run_oracle(world, replace(test, num_worlds=50)) if world.obstacles.count else None
    return References(
        random.fractions(), blind.fractions(), None if oracle is None else oracle.fractions()
    )


def _study_axes(
    args: argparse.Namespace,
) -> tuple[tuple[str, ...], tuple[str, ...], tuple[int, ...]]:
    """The scenarios, models and seeds a study's options name (`reproduce` and `sweep`)."""
    from qnav.training.study import MODELS, SCENARIOS, parse_choices, parse_seeds

    return (
        parse_choices("--scenarios", args.scenarios, SCENARIOS),
        parse_choices("--models", args.models, MODELS),
        parse_seeds(args.seeds),
    )


def _run_study(
    args: argparse.Namespace, specs: list[RunSpec], common: tuple[str, ...] = ()
) -> None:
    """Train the study's missing runs with the engine, threads, jobs and budget its options ask
    for (`qnav reproduce` and `qnav sweep` alike)."""
    from qnav.training.study import run_study

    budget = None if args.time_budget_min is None else args.time_budget_min * 60
    run_study(
        specs,
        args.runs_dir,
        results_root=args.results_dir,
        jobs=args.jobs,
        threads=_threads(args),
        preset=args.preset,
        time_budget_s=budget,
        common=common,
        engine=_engine(args),
    )


def _threads(args: argparse.Namespace) -> int | None:
    """Torch threads per run: as given; else on Ray 2 (the fast preset's, sized for any node),
    else the local runner shares this machine's cores among its jobs (None)."""
    if args.threads is not None or args.engine == "local":
        return int(args.threads) if args.threads is not None else None
    return 2


def _engine(args: argparse.Namespace) -> Callable[[StudySettings], Engine] | None:
    """The engine a study's options ask for: None for the local runner, else Ray's."""
    from qnav.options import given_settings

    if args.engine == "local":
        given = sorted(given_settings(args))
        if given:
            options = ", ".join("--" + name.replace("_", "-") for name in given)
            raise ConfigError(f"{options} {'needs' if len(given) == 1 else 'need'} --engine ray")
        return None
    from qnav.cli import main
    from qnav.training.cluster import ClusterSettings, RayEngine, parse_address

    settings = settings_from_args(ClusterSettings(), args)
    if settings.address is not None:
        parse_address(settings.address)  # a malformed one is named before anything else
    return lambda study: RayEngine(args.runs_dir, study, settings, main)


def sweep(args: argparse.Namespace) -> int:
    """Train every point of a settings grid, then print each run's test figures."""
    from qnav.training.study import parse_grid, sweep_plan, sweep_table

    grid = parse_grid(args.grid)
    specs = sweep_plan(*_study_axes(args), grid)
    _run_study(args, specs, common=tuple(args.common))
    print(sweep_table(specs, args.results_dir))
    return 0


def figures(args: argparse.Namespace) -> int:
    """Action maps and trajectories of a training run, as PNG."""
    from qnav.training.figures import write_figures

    for path in write_figures(args.run, args.out):
        print(f"wrote {path}")
    return 0


def add_verbs(verbs: Verbs) -> None:
    """`qnav train`, `export`, `figures`, `reproduce` and `sweep`: their options."""
    _add_train(verbs)
    _add_export(verbs)
    _add_figures(verbs)
    _add_reproduce(verbs)
    _add_sweep(verbs)


def _add_train(verbs: Verbs) -> None:
    """`qnav train`: the learner's settings over a preset."""
    parser = verb(verbs, train, "train", help="train a Q-network (resumes a killed run)")
    world_options(parser)
    parser.add_argument(
        "--preset",
        default="fast",
        choices=list(PRESETS),
        help="fast: our schedule for 2 CPU cores (default); paper: the paper's exact schedule; "
        "dagger: imitation of the planner given the map (worlds of layouts: the clutter scenario)",
    )
    parser.add_argument(
        "--train-config", type=Path, metavar="FILE", help="TOML file with a [train] table"
    )
    repeated(
        parser,
        "--train-set",
        "train_assignments",
        "train.FIELD=VALUE",
        "change one learner setting (repeatable; as its option below)",
    )
    settings_options(
        parser,
        "qnav.training.config:TrainSettings",
        "learner settings (each over the preset, --train-config and --train-set)",
    )
    parser.add_argument("--run-dir", type=Path, help="run folder (default runs/SCENARIO/...)")
    flag(parser, "--quiet", "no progress bar")
    add_print_config(parser)


def _add_export(verbs: Verbs) -> None:
    """`qnav export RUN`."""
    parser = verb(
        verbs,
        export,
        "export",
        help="write a run's policy as one ONNX file with its contract, and test it",
    )
    parser.add_argument(
        "run",
        type=Path,
        help="training run folder, or a policy file (.onnx, e.g. of the earlier "
        "qnav-policy/1 layout) to export again in this layout from its own weights",
    )
    parser.add_argument(
        "-o", "--output", type=Path, default=None, help="policy file (default RUN/policy.onnx)"
    )
    parser.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        help="test-protocol episodes run on the exported file and recorded in it (0: none; "
        "default 200 for a run or a change of --weights, else 0 for a policy file, whose "
        "recorded results are kept)",
    )
    parser.add_argument(
        "--turn-commitment",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the runtime never reverses its previous turn before driving forward (for "
        "policies imitating the planner given the map, which dither between turns without it: "
        "docs/barn.md); default: as the run trained (imitation.turn_commitment), as in the "
        "source for a policy file",
    )
    parser.add_argument(
        "--weights",
        choices=WEIGHT_TYPES,
        default=None,
        help="how the large weights are stored: float32, or int8 (a quarter of the bytes, "
        "quicker decisions; its test records how often it agrees with float32). Default: "
        "float32 for a run, the file's own for a policy file",
    )
    flag(parser, "--quiet", "no progress bar")


def _add_figures(verbs: Verbs) -> None:
    """`qnav figures RUN`."""
    parser = verb(
        verbs,
        figures,
        "figures",
        help="action maps (paper figure 3) and trajectories (figure 10) of a run",
    )
    parser.add_argument("run", type=Path, help="training run folder")
    parser.add_argument("--out", type=Path, default=Path("docs/img"), help="output folder")


def _add_reproduce(verbs: Verbs) -> None:
    """`qnav reproduce`: the paper's study."""
    parser = verb(
        verbs,
        reproduce,
        "reproduce",
        help="the paper's whole study, resumable: trains, tests, writes the tables",
    )
    study_options(parser, Path("runs/study"))
    parser.add_argument(
        "--results-dir", type=Path, default=Path("results"), help="one JSON per run (committed)"
    )
    parser.add_argument(
        "--docs", type=Path, default=Path("docs/results.md"), help="the tables, as Markdown"
    )
    flag(
        parser,
        "--ablation",
        "also run the target re-drawing ablation (none / paper / hindsight) in the chosen "
        "scenarios among walls-increment and obstacles-inertia",
    )
    parser.add_argument(
        "--ablation-seeds", default="0", help="comma-separated seeds of the ablation runs (0)"
    )
    flag(parser, "--tables-only", "rewrite the tables from results/, train nothing")


def _add_sweep(verbs: Verbs) -> None:
    """`qnav sweep`: a grid of settings."""
    parser = verb(
        verbs,
        sweep,
        "sweep",
        help="train every point of a settings grid (resumable; locally or on Ray)",
    )
    study_options(parser, Path("runs/sweep"), scenarios="walls-inertia", models="recurrent",
                   seeds="0")  # fmt: skip
    parser.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="SECTION.FIELD=V1,V2,...",
        help="one setting and its values, e.g. --grid train.learning_rate=1e-4,3e-4 (repeatable: "
        "every combination is a run; train.* are learner settings, other sections the world's)",
    )
    repeated(
        parser,
        "--set",
        "common",
        "SECTION.FIELD=VALUE",
        "a setting of every run, e.g. --set train.episodes=100 (repeatable)",
    )
    parser.add_argument(
        "--results-dir",
        type=Path,
        default=Path("runs/sweep/results"),
        help="one JSON per run (a run with one is skipped)",
    )


def study_options(
    parser: Parser,
    runs_dir: Path,
    scenarios: str = "obstacles-inertia,walls-inertia,walls-increment,obstacles-increment",
    models: str = "recurrent,feedforward",
    seeds: str = "0,1,2,3,4",
) -> None:
    """What runs a study or a sweep, and where: its plan, the local runner or Ray."""
    parser.add_argument("--jobs", type=int, default=1, help="local runner: trainings at once (1)")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads per training, and CPUs of its Ray task (default: the machine's "
        "cores / --jobs; with --engine ray, 2)",
    )
    parser.add_argument("--preset", default="fast", choices=list(PRESETS), help="schedule")
    parser.add_argument("--scenarios", default=scenarios, help=f"comma-separated ({scenarios})")
    parser.add_argument("--models", default=models, help=f"comma-separated models ({models})")
    parser.add_argument("--seeds", default=seeds, help=f"comma-separated seeds ({seeds})")
    parser.add_argument(
        "--time-budget-min",
        type=float,
        default=None,
        help="start no new run after this many minutes (the rest waits for the next batch)",
    )
    parser.add_argument(
        "--runs-dir",
        type=Path,
        default=runs_dir,
        help=f"run folders ({runs_dir}); on a cluster without --artifacts, a path every node "
        "shares",
    )
    engine = parser.add_argument_group("engine (docs/cluster.md)")
    engine.add_argument(
        "--engine",
        default="local",
        choices=["local", "ray"],
        help="local: `qnav train` processes on this machine (default); ray: one Ray task per run "
        "(pip install '.[cluster]')",
    )
    settings_options(
        parser,
        "qnav.training.cluster:ClusterSettings",
        "Ray settings (with --engine ray)",
    )
