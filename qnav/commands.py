"""Handlers of the verbs that join packages: eval (random agent or a trained policy), train."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import load_toml, parse_assignments, with_overrides
from qnav.options import settings_from_args
from qnav.sim.config import WorldConfig, load_world
from qnav.sim.evaluate import Agent, EvalSettings, GoToTargetAgent, RandomAgent, StreamPolicyAgent
from qnav.sim.evaluate import evaluate as run_evaluation

if TYPE_CHECKING:
    from qnav.lab.imitate import ImitationResult
    from qnav.lab.imitation_settings import ImitationSettings
    from qnav.lab.probe import PerceptionSettings
    from qnav.training.study import Engine, RunSpec, StudySettings


def evaluate(args: argparse.Namespace) -> int:
    """The paper's test protocol with the random agent or a trained policy."""
    eval_settings = settings_from_args(EvalSettings(), args)
    seed = eval_settings.seed
    worlds = min(eval_settings.num_worlds, eval_settings.episodes)
    agent: Agent
    if args.policy is not None and args.policy.suffix == ".onnx":
        from qnav.controller.policy import Expectation, PolicyRuntime

        probe = PolicyRuntime(args.policy, backend=args.backend)
        world = load_world(
            args.scenario or probe.contract.scenario, args.world_config, args.assignments
        )
        expect = Expectation(
            num_beams=world.lidar.num_beams if world.lidar else 0,
            control_period_s=world.control_period_s,
        )
        runtime = PolicyRuntime(
            args.policy, backend=args.backend, num_streams=worlds, expect=expect
        )
        agent = StreamPolicyAgent(runtime, worlds, args.random_action_prob, seed=seed)
        label = f"policy file {args.policy} ({args.backend})"
    elif args.policy is None:
        world = load_world(args.scenario or "walls-inertia", args.world_config, args.assignments)
        agent, label = (
            (RandomAgent(worlds, seed=seed), "random agent")
            if args.agent == "random"
            else (GoToTargetAgent(), "go-to-target baseline")
            if args.agent == "goto"
            else (RandomAgent(worlds, seed=seed), "oracle planner (knows the future)")
        )
    else:
        from qnav.training.agent import policy_agent
        from qnav.training.policy import load_network

        network, run = load_network(args.policy)
        world = (
            load_world(args.scenario, args.world_config, args.assignments)
            if args.scenario
            else run.world
        )
        agent = policy_agent(
            network,
            world,
            worlds,
            run.train.window,
            epsilon=args.random_action_prob,
            hold_steps=1,
            seed=seed,
        )
        label = f"{run.train.model} policy {args.policy}"
    planner = args.policy is None and args.agent == "oracle"
    if args.state_error and not planner:
        raise ConfigError("--state-error is for --agent oracle (the planner's view of the state)")
    if args.tracker and not planner:
        raise ConfigError("--tracker is for --agent oracle (with --policy, use --lookahead)")
    if args.state_error and args.tracker:
        raise ConfigError("--state-error and --tracker are two views of the state: choose one")
    looking = args.lookahead != "off"
    if looking and (args.policy is None or args.random_action_prob):
        raise ConfigError(
            "--lookahead runs beside a greedy policy: give --policy, no random actions"
        )
    if args.range_noise_m and not (args.tracker or looking):
        raise ConfigError(
            "--range-noise-m is the noise the tracker reads: give --tracker or --lookahead"
        )
    if args.range_noise_m < 0:
        raise ConfigError(
            f"--range-noise-m = {args.range_noise_m} is out of range: allowed [0, inf)"
        )
    shield = None
    if looking:
        from qnav.controller.lookahead import LookaheadSettings
        from qnav.controller.perception import TrackerSettings
        from qnav.tracking import LookaheadAgent, QAgent

        shield = agent = LookaheadAgent(
            cast(QAgent, agent),  # --policy gave a StreamPolicyAgent or a TorchAgent
            world,
            worlds,
            tracker=TrackerSettings(),
            lookahead=LookaheadSettings(mode=args.lookahead),
            range_noise_m=args.range_noise_m,
            seed=seed,
        )
        label += f", the controller's look ahead in {args.lookahead} mode"
    if args.random_action_prob:
        label += f" with {args.random_action_prob:.0%} random actions"
    if planner and args.tracker:
        from qnav.controller.perception import TrackerSettings
        from qnav.lab.tracking import run_perceiving_oracle

        label += ", planning on the onboard tracker's estimate"
        result = run_perceiving_oracle(
            world,
            eval_settings,
            TrackerSettings(),
            range_noise_m=args.range_noise_m,
            progress=not args.json,
        )
    elif planner:
        from qnav.lab.oracle import PERCEPTION_LEVELS, run_oracle

        error = PERCEPTION_LEVELS[args.state_error] if args.state_error else None
        if error is not None:
            label += f", planning on a {args.state_error} estimate of the state"
        result = run_oracle(world, eval_settings, state_error=error, progress=not args.json)
    else:
        result = run_evaluation(world, agent, eval_settings, progress=not args.json)
    if args.json:
        print(json.dumps({k: v for k, v in asdict(result).items() if k != "mean_steps"}))
        return 0
    steps = eval_settings.max_episode_steps
    print(f"{world.name}, {label}, {result.episodes} episodes of up to {steps} steps")
    for name in ("success", "collision", "unfinished"):
        value = getattr(result, name)
        print(f"  {name:<11} {value:.3f} +- {result.standard_error(value):.3f}")
    print(f"  mean length {result.mean_steps:.1f} steps")
    if shield is not None:
        print(f"  overruled  {shield.overruled_share:.3f} of the policy's decisions")
    return 0


def train(args: argparse.Namespace) -> int:
    """Train (or resume) one run."""
    from qnav.training.config import preset
    from qnav.training.run import train as run_training

    world: WorldConfig = load_world(args.scenario, args.world_config, args.assignments)
    settings = preset(args.preset, world)
    if args.train_config is not None:
        settings = with_overrides(settings, load_toml(args.train_config).get("train", {}))
    settings = settings_from_args(settings, args, assignments=args.train_assignments)
    run_dir = args.run_dir or Path("runs") / world.name / (
        f"{settings.model}-seed{settings.seed}-{args.preset}"
        + ("" if settings.relabel == "paper" else f"-{settings.relabel}")
    )
    print(f"run folder: {run_dir}")
    # The decisive-state gauge comes from the lab (it needs the oracle planner): the shell hands
    # it to the run, which knows only the protocol (training.validation.Gauge).
    from qnav.lab.gauge import training_gauge

    gauge = training_gauge(world, settings, progress=not args.quiet)
    results = run_training(world, settings, run_dir, progress=not args.quiet, gauge=gauge)
    test = results["test"]
    print(
        f"test ({test['episodes']} episodes of up to 500 steps): success {test['success']:.3f}, "
        f"collision {test['collision']:.3f}, unfinished {test['unfinished']:.3f}"
    )
    print(f"wrote {run_dir}/results.json, progress.csv, success.png, model.pt")
    return 0


def bench_learner(args: argparse.Namespace) -> int:
    """Training iteration cost against the machine's own matrix-product rate."""
    from qnav.training.bench import format_report, run

    report = run(
        model=args.model, batch_size=args.batch, repeats=args.repeats, threads=args.threads
    )
    print(json.dumps(report) if args.json else format_report(report))
    return 0


def reproduce(args: argparse.Namespace) -> int:
    """Run the study's missing runs, then write docs/results.md."""
    from qnav.sim import paper
    from qnav.sim.config import scenario
    from qnav.training.study import (
        MODELS,
        SCENARIOS,
        ablation_plan,
        parse_choices,
        parse_seeds,
        plan,
        results_markdown,
    )

    seeds = parse_seeds(args.seeds)
    scenarios = parse_choices("--scenarios", args.scenarios, SCENARIOS)
    models = parse_choices("--models", args.models, MODELS)
    specs = plan(scenarios, models, seeds)
    if args.ablation:
        ablation_seeds = parse_seeds(args.ablation_seeds, "--ablation-seeds")
        specs += [s for s in ablation_plan(ablation_seeds) if s.scenario in scenarios]
    if not args.tables_only:
        _run_study(args, specs)
    random_rows = {}
    for name in paper.RANDOM:
        result = run_evaluation(
            scenario(name),
            RandomAgent(250, seed=1),
            EvalSettings(episodes=1000, num_worlds=250),
            progress=False,
        )
        random_rows[name] = asdict(result)
    args.docs.parent.mkdir(parents=True, exist_ok=True)
    args.docs.write_text(results_markdown(args.results_dir, random_rows))
    print(f"wrote {args.docs}")
    return 0


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
    from qnav.training.cluster import ClusterSettings, RayEngine, parse_address

    settings = settings_from_args(ClusterSettings(), args)
    if settings.address is not None:
        parse_address(settings.address)  # a malformed one is named before anything else
    return lambda study: RayEngine(args.runs_dir, study, settings)


def sweep(args: argparse.Namespace) -> int:
    """Train every point of a settings grid, then print each run's test figures."""
    from qnav.training.study import (
        MODELS,
        SCENARIOS,
        parse_choices,
        parse_grid,
        parse_seeds,
        sweep_plan,
        sweep_table,
    )

    grid = parse_grid(args.grid)
    scenarios = parse_choices("--scenarios", args.scenarios, SCENARIOS)
    specs = sweep_plan(
        scenarios, parse_choices("--models", args.models, MODELS), parse_seeds(args.seeds), grid
    )
    _run_study(args, specs, common=tuple(args.common))
    print(sweep_table(specs, args.results_dir))
    return 0


def calibrate(args: argparse.Namespace) -> int:
    """Random, go-to-target and oracle agents in each paper scenario, beside the paper's rows."""
    from qnav.lab.calibrate import calibrate as measure
    from qnav.lab.calibrate import table
    from qnav.sim import paper
    from qnav.sim.config import scenario

    worlds = {name: scenario(name) for name in paper.RANDOM}
    rows = measure(
        worlds,
        episodes=args.episodes,
        oracle_episodes=args.oracle_episodes,
        seed=args.seed,
        progress=not args.json,
    )
    if args.json:
        print(json.dumps([row.as_dict() for row in rows]))
        return 0
    print(
        f"{args.episodes} episodes of up to 500 steps per scenario for random and go-to-target, "
        f"{args.oracle_episodes} for the oracle (seed {args.seed})\n"
    )
    print(table(rows))
    return 0


def figures(args: argparse.Namespace) -> int:
    """Action maps and trajectories of a training run, as PNG."""
    from qnav.training.figures import write_figures

    for path in write_figures(args.run, args.out):
        print(f"wrote {path}")
    return 0


def diagnose(args: argparse.Namespace) -> int:
    """Generalisation gap, target sensitivity and action mix of a training run."""
    from qnav.lab.diagnose import diagnose as measure

    print(measure(args.run, fresh_episodes=args.fresh_episodes).render())
    return 0


def gauge(args: argparse.Namespace) -> int:
    """The decisive states of a world with the baselines' scores, or each run's score on its
    own world's states beside its test success."""
    from qnav.contracts.actions import Action
    from qnav.lab.decisive import (
        GaugeResult,
        GaugeSettings,
        cached,
        constant_choice,
        go_to_target_choices,
        perception_ceiling,
        random_expectation,
    )
    from qnav.lab.decisive import score as judge
    from qnav.lab.oracle import PERCEPTION_LEVELS

    rows: list[dict[str, object]] = []
    if not args.runs:
        world = load_world(args.scenario, args.world_config, args.assignments)
        if not world.obstacles.count:
            raise ConfigError(f"scenario {world.name!r} has no moving obstacles: nothing is doomed")
        states = cached(world, GaugeSettings(episodes_per_driver=args.episodes), progress=True)
        if len(states.doomed) == 0:
            raise ConfigError(
                f"no decisive states in {states.visited.sum()} visited: raise --episodes"
            )
        baselines: list[tuple[str, GaugeResult]] = [
            ("random", random_expectation(states)),
            ("go-to-target", judge(states, go_to_target_choices(states))),
            *((f"always {a.name.lower()}", constant_choice(states, a)) for a in Action),
        ]
        if args.ceiling:
            baselines += [
                (f"best choice, {level} state", perception_ceiling(world, states, error))
                for level, error in PERCEPTION_LEVELS.items()
            ]
        for name, result in baselines:
            rows.append(
                {
                    "policy": name,
                    "safe": result.safe,
                    "balanced": result.balanced,
                    **result.by_driver,
                }
            )
        visited = dict(zip(("planner", "go-to-target"), states.visited.tolist(), strict=True))
        print(
            f"{len(states.doomed)} decisive states in {sum(visited.values())} visited "
            f"(planner {visited['planner']}, go-to-target {visited['go-to-target']})"
        )
    for run in args.runs:
        from qnav.lab.diagnose import decisive_report
        from qnav.lab.gauge import decisive_states
        from qnav.training.policy import load_network

        network, settings = load_network(run)
        train = replace(settings.train, gauge_episodes=args.episodes)
        world = replace(settings.world, max_episode_steps=train.max_episode_steps)
        report = decisive_report(network, decisive_states(world, train, progress=True))
        results = run / "results.json"
        test = json.loads(results.read_text())["test"]["success"] if results.exists() else None
        rows.append(
            {
                "policy": str(run),
                "safe": report.safe,
                "balanced": report.balanced,
                **report.by_driver,
                "test_success": test,
            }
        )
    for row in rows:
        if args.json:
            print(json.dumps(row))
        else:
            shares = ", ".join(
                f"{key} {value:.3f}" for key, value in row.items() if isinstance(value, float)
            )
            print(f"{row['policy']}: {shares}")
    return 0


def probe(args: argparse.Namespace) -> int:
    """Fit the paper's network to the planner's doom labels and print the gauge after each pass,
    or (--perception) fit it to locate the nearest obstacle and print the median errors."""
    from qnav.contracts.settings import to_toml
    from qnav.lab.probe import PerceptionSettings, ProbeSettings
    from qnav.lab.probe import probe as fit

    if args.tracker:
        return _track(args)
    settings: ProbeSettings | PerceptionSettings
    [settings] = _probe_set(
        args.probe_assignments, PerceptionSettings() if args.perception else ProbeSettings()
    )
    if args.print_config:
        print(to_toml(settings))
        return 0
    world = load_world(args.scenario, args.world_config, args.assignments)
    if not world.obstacles.count:
        raise ConfigError(f"scenario {world.name!r} has no moving obstacles: nothing is doomed")
    if isinstance(settings, PerceptionSettings):
        return _perceive(world, settings, args.json)
    for epoch in fit(world, settings, progress=not args.json):
        if args.json:
            print(json.dumps(epoch._asdict()))
        else:
            print(
                f"epoch {epoch.epoch}: loss {epoch.loss:.4f}, fit (balanced, training set) "
                f"{epoch.train_balanced:.3f}, gauge safe {epoch.safe:.3f}, "
                f"balanced {epoch.balanced:.3f} (blind choices 0.500)"
            )
    return 0


def _probe_set(assignments: list[str], *defaults: Any) -> list[Any]:
    """Each settings object of `defaults` with the `--probe-set SECTION.FIELD=VALUE` changes
    to its SECTION; a section none of them has is an error naming the ones there are."""
    if not assignments:
        return list(defaults)
    overrides = parse_assignments(assignments)
    sections = [settings.SECTION for settings in defaults]
    unknown = set(overrides) - set(sections)
    if unknown:
        allowed = " or ".join(f"{section}.FIELD=VALUE" for section in sections)
        raise ConfigError(f"--probe-set takes {allowed}, not {sorted(unknown)}")
    return [
        with_overrides(settings, overrides.get(section, {}), section)
        for settings, section in zip(defaults, sections, strict=True)
    ]


def _track(args: argparse.Namespace) -> int:
    """The onboard tracker's errors on the perception probe's drive."""
    from qnav.contracts.settings import to_toml
    from qnav.controller.perception import TrackerSettings
    from qnav.lab.tracking import TrackerCheckSettings, measure_tracker

    tracker: TrackerSettings
    check: TrackerCheckSettings
    tracker, check = _probe_set(args.probe_assignments, TrackerSettings(), TrackerCheckSettings())
    if args.print_config:
        print(
            f"[{tracker.SECTION}]\n{to_toml(tracker)}\n[{check.SECTION}]\n{to_toml(check)}", end=""
        )
        return 0
    world = load_world(args.scenario, args.world_config, args.assignments)
    errors = measure_tracker(world, tracker, check, progress=not args.json)
    if args.json:
        print(json.dumps(errors._asdict()))
        return 0
    print(
        f"{world.name}: the onboard tracker on {errors.samples} states (nearest obstacle within "
        f"{check.max_distance_m} m), lidar range noise {check.range_noise_m} m"
    )
    for name in errors.median:
        print(f"  {name:<22} median {errors.median[name]:.4f}  p90 {errors.p90[name]:.4f}")
    print(f"  no track within 1 m of the nearest obstacle: {errors.missed_share:.3f}")
    print(
        f"  one update (one scan) takes {errors.update_ms[0]:.2f} ms median, "
        f"{errors.update_ms[1]:.2f} ms p99, on this machine"
    )
    return 0


def _perceive(world: WorldConfig, settings: PerceptionSettings, as_json: bool) -> int:
    from qnav.lab.probe import perceive

    for epoch in perceive(world, settings, progress=not as_json):
        if as_json:
            print(json.dumps(epoch._asdict()))
        else:
            name = f"epoch {epoch.epoch}" if epoch.epoch else "predicting the mean"
            errors = ", ".join(f"{key} {value:.3f}" for key, value in epoch.errors.items())
            print(f"{name}: median absolute error {errors}")
    return 0


def imitate(args: argparse.Namespace) -> int:
    """Copy the oracle planner with the learner's network; test the copy."""
    from qnav.lab.imitate import imitate as measure
    from qnav.lab.imitation_settings import ImitationSettings

    world: WorldConfig = load_world(args.scenario, args.world_config, args.assignments)
    settings = settings_from_args(ImitationSettings(), args)
    if args.privileged:
        from qnav.lab.privileged import imitate_privileged

        result = imitate_privileged(world, settings)
    else:
        result = measure(world, settings, args.window)
    if args.json:
        print(json.dumps(result.to_dict()))
        return 0
    print(_imitation_report(world.name, settings, result, privileged=args.privileged))
    return 0


def _imitation_report(
    world: str, settings: ImitationSettings, result: ImitationResult, *, privileged: bool
) -> str:
    copy = "a network given the world's state" if privileged else settings.model
    test = result.test
    lines = [
        f"{world}, {copy}: planner success {result.planner_success:.3f} on the "
        f"{settings.episodes} copied episodes ({result.windows} decisions)",
        f"clone agrees with the planner on {result.train_agreement:.1%} of copied decisions, "
        f"{result.held_out_agreement:.1%} of held-out ones",
    ]
    if result.planner_self_agreement is not None:
        lines.append(
            "the planner, asked again on the held-out states, picks the same action on "
            f"{result.planner_self_agreement:.1%} of them"
        )
    lines += [
        f"dodges (the planner's action is not go-to-target's): {result.dodge_share:.1%} of "
        f"held-out decisions; the clone copies {result.dodge_agreement:.1%} of them and goes to "
        f"the target instead on {result.dodge_as_baseline:.1%}",
        f"clone, test protocol ({test.episodes} episodes of up to 500 steps): success "
        f"{test.success:.3f}, collision {test.collision:.3f}, unfinished {test.unfinished:.3f}",
    ]
    lines += [
        f"DAgger round {r['round']}: {r['windows']} decisions, test success {r['test_success']:.3f}"
        for r in result.dagger
    ]
    lines.append(f"{result.minutes} minutes")
    return "\n".join(lines)


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
        )
    else:
        output = args.output or args.run / "policy.onnx"
        contract = export_run(
            args.run,
            output,
            eval_episodes=episodes,
            weight_type=args.weights or "float32",
            progress=not args.quiet,
        )
    print(
        f"wrote {output} ({output.stat().st_size / 1e6:.1f} MB, {contract.weight_type} weights "
        "inside)"
    )
    print(
        f"  {contract.model_kind}, {contract.scenario}, window {contract.window_length}, "
        f"{contract.num_beams} beams, period {contract.control_period_s} s"
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


def bench_lookahead(args: argparse.Namespace) -> int:
    """Per-decision wall time of the controller's look ahead."""
    from qnav.tracking import time_lookahead

    world = load_world(args.scenario, args.world_config, args.assignments)
    report = time_lookahead(world, args.decisions)
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"{world.name}, {report['decisions']:.0f} decisions, one car at a time (ms):")
    for name in ("track", "shield", "plan"):
        print(
            f"  {name:<7} p50 {report[name + '_ms_p50']:6.1f}  p99 {report[name + '_ms_p99']:6.1f}"
        )
    return 0


def bench_policy(args: argparse.Namespace) -> int:
    """Per-decision latency of each runtime backend."""
    import tempfile

    from qnav.controller.bench import format_report, run

    with tempfile.TemporaryDirectory() as scratch:
        policy = args.policy or _paper_sized_policy(Path(scratch), args.weights)
        report = run(policy, args.backends.split(","), args.decisions, args.gap_ms / 1e3)
        if args.policy is None:
            report["policy"] = f"{PAPER_SIZED}, {args.weights} weights"
    print(json.dumps(report) if args.json else format_report(report))
    return 0


PAPER_SIZED = "untrained paper-sized recurrent (720 beams, LSTM 512, k = 5)"


def _paper_sized_policy(folder: Path, weight_type: str = "float32") -> Path:
    """An untrained policy file of the paper's size (the benches time its arithmetic)."""
    from qnav.sim.config import scenario
    from qnav.training.export import export_onnx, policy_contract
    from qnav.training.networks import QNetwork

    world = scenario("obstacles-inertia")
    network = QNetwork("recurrent", 720)
    policy = folder / f"paper-sized-{weight_type}.onnx"
    contract = policy_contract(network, world, 5, "untrained (bench)", "", weight_type=weight_type)
    export_onnx(network, contract, policy)
    return policy


def bench_controller(args: argparse.Namespace) -> int:
    """End-to-end latency of the controller daemon: scan published -> command received."""
    import tempfile

    from qnav.controller.bench_e2e import format_report, run

    rates = [float(r) for r in args.rates.split(",")]
    with tempfile.TemporaryDirectory() as scratch:
        policy = args.policy or _paper_sized_policy(Path(scratch), args.weights)
        report = run(policy, rates, args.seconds)
        if args.policy is None:
            report["policy"] = f"{PAPER_SIZED}, {args.weights} weights"
    print(json.dumps(report) if args.json else format_report(report))
    return 0


def health(args: argparse.Namespace) -> int:
    """`qnav health`: 0 while the daemon's loop beats (a container HEALTHCHECK), 1 otherwise."""
    import sys

    from qnav.contracts.health import HEALTH_FILE_ENV, check_health, health_path

    path = args.file or health_path()
    if path is None:
        print(f"qnav health: give --file or set {HEALTH_FILE_ENV}", file=sys.stderr)
        return 2
    healthy, explanation = check_health(path, args.max_age_s)
    print(f"{'healthy' if healthy else 'unhealthy'}: {explanation}")
    return 0 if healthy else 1
