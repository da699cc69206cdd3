"""Handlers of `qnav lab`: the research tools of lab/ (calibrate, diagnose, gauge, audit, probe,
label, imitate)."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from qnav.contracts.errors import ConfigError
from qnav.contracts.settings import parse_assignments, with_overrides
from qnav.options import config_text, settings_from_args
from qnav.sim.config import WorldConfig, load_world

if TYPE_CHECKING:
    from qnav.lab.doubt import FinalTest, RoundReport
    from qnav.lab.imitate import ImitationResult
    from qnav.lab.imitation_settings import ImitationSettings
    from qnav.lab.probe import PerceptionSettings, ProbeSettings, ShieldTest


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


def diagnose(args: argparse.Namespace) -> int:
    """Generalisation gap, target sensitivity and action mix of a training run."""
    from qnav.lab.diagnose import diagnose as measure

    print(measure(args.run, fresh_episodes=args.fresh_episodes).render())
    return 0


def audit(args: argparse.Namespace) -> int:
    """A run's policy driven under each judgement of doom, its decisive states counted."""
    from qnav.lab.audit import JUDGEMENTS, Judgement
    from qnav.lab.audit import audit as drive
    from qnav.sim.evaluate import EvalSettings
    from qnav.training.study import parse_choices

    judgements = JUDGEMENTS
    if args.judgements is not None:
        # parse_choices keeps only names of JUDGEMENTS, so each is a Judgement.
        judgements = cast(
            tuple[Judgement, ...], parse_choices("--judgements", args.judgements, JUDGEMENTS)
        )
    protocol = EvalSettings(episodes=args.episodes, seed=args.seed)
    audits = drive(args.run, protocol, args.judge, progress=not args.json, judgements=judgements)
    if args.json:
        for row in audits:
            print(
                json.dumps(
                    {
                        **row._asdict(),
                        "result": row.result.fractions(),
                        "decisive_per_episode": row.decisive_per_episode,
                    }
                )
            )
        return 0
    layouts = f"{args.episodes} episodes (seed {args.seed})"
    print(f"the greedy policy of {args.run} in its world, {layouts}")
    if args.judge is not None:
        print(f"  judge file: {args.judge}")
    print(
        f"  {'judgement':<24} success  decisive states  per episode  taken safe  policy safe  "
        "overruled"
    )
    for row in audits:
        print(
            f"  {row.judgement:<24} {row.result.success:7.3f}  {row.decisive:15d}  "
            f"{row.decisive_per_episode:11.2f}  {row.taken_safe:10.3f}  "
            f"{row.policy_safe:11.3f}  {row.overruled:9.3f}"
        )
    return 0


def gauge(args: argparse.Namespace) -> int:
    """The decisive states of a world with the baselines' scores, or each run's score on its
    own world's states beside its test success."""
    from qnav.contracts.actions import Action
    from qnav.lab.decisive import (
        DRIVERS,
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
        visited = dict(zip(DRIVERS, states.visited.tolist(), strict=True))
        print(
            f"{len(states.doomed)} decisive states in {sum(visited.values())} visited "
            f"(planner {visited['planner']}, go-to-target {visited['go-to-target']})"
        )
    for run in args.runs:
        from qnav.lab.diagnose import decisive_report
        from qnav.lab.gauge import decisive_states
        from qnav.training.run_folder import load_network

        network, settings = load_network(run)
        train = replace(settings.train, gauge_episodes=args.episodes)
        world = replace(settings.world, max_episode_steps=train.max_episode_steps)
        report = decisive_report(
            network, decisive_states(world, train, progress=True), world, train.gamma
        )
        results = run / "results.json"
        test = json.loads(results.read_text())["test"]["success"] if results.exists() else None
        rows.append(
            {
                "policy": str(run),
                "safe": report.safe,
                "balanced": report.balanced,
                **report.by_driver,
                "value_gap": report.value_gap,
                "target_ranks_safe": report.target_ranks_safe,
                "target_gap": report.target_gap,
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
    from qnav.lab.probe import PerceptionSettings, ProbeSettings, shield_test
    from qnav.lab.probe import probe as fit

    if args.tracker:
        return _track(args)
    settings: ProbeSettings | PerceptionSettings
    [settings] = _probe_set(
        args.probe_assignments, PerceptionSettings() if args.perception else ProbeSettings()
    )
    if args.print_config:
        print(config_text(settings), end="")
        return 0
    world = load_world(args.scenario, args.world_config, args.assignments)
    if not world.obstacles.count:
        raise ConfigError(f"scenario {world.name!r} has no moving obstacles: nothing is doomed")
    if isinstance(settings, PerceptionSettings):
        return _perceive(world, settings, args.json)
    fitted = fit(world, settings, progress=not args.json)
    sizes = {
        "labelled_states": fitted.labelled_states,
        "labelled_decisive": fitted.labelled_decisive,
        "held_out_decisive": fitted.held_out_decisive,
    }
    if args.json:
        print(json.dumps(sizes))
    else:
        print(
            f"fitted to {fitted.labelled_states:,} labelled states "
            f"({fitted.labelled_decisive:,} decisive); judged on "
            f"{fitted.held_out_decisive:,} held-out decisive states"
        )
    for epoch in fitted.history:
        if args.json:
            print(json.dumps(epoch._asdict()))
        else:
            print(
                f"epoch {epoch.epoch}: loss {epoch.loss:.4f}, fit (balanced, training set) "
                f"{epoch.train_balanced:.3f}, gauge safe {epoch.safe:.3f}, "
                f"balanced {epoch.balanced:.3f} (blind choices 0.500)"
            )
    if settings.shield_episodes:
        test = shield_test(world, fitted, settings, progress=not args.json)
        _print_shield_test(test, args.json)
    return 0


def label(args: argparse.Namespace) -> int:
    """Rounds of doubt-led labelling in a folder, each refitted, gauged and shield-tested."""
    from qnav.lab.decisive import GaugeSettings
    from qnav.lab.doubt import LABEL_PROBE, DoubtSettings, run_rounds

    if args.rounds < 0 or args.test_episodes < 0:
        raise ConfigError(
            f"--rounds and --test-episodes must be 0 or more, not {args.rounds} and "
            f"{args.test_episodes}"
        )
    probe_settings, doubt, gauge = _probe_set(
        args.probe_assignments, LABEL_PROBE, DoubtSettings(), GaugeSettings()
    )
    if args.print_config:
        print(config_text(probe_settings, doubt, gauge), end="")
        return 0
    if args.folder is None:
        raise ConfigError("qnav lab label needs a FOLDER for its rounds")
    if args.export and not args.test_episodes:
        raise ConfigError(
            "--export writes the fit with the threshold its final test chooses: give "
            "--test-episodes N too"
        )
    world = load_world(args.scenario, args.world_config, args.assignments)
    reports = run_rounds(
        world,
        args.folder,
        args.rounds,
        probe=probe_settings,
        settings=doubt,
        gauge=gauge,
        progress=not args.json,
    )
    if not args.json:
        print(
            f"{world.name}: doubt-led labelling in {args.folder}, up to round {args.rounds} "
            f"(round 0: the probe's labelled set alone)"
        )
    finished: list[RoundReport] = []
    for report in reports:
        finished.append(report)
        if args.json:
            print(json.dumps(report._asdict()), flush=True)
            continue
        print(
            f"round {report.round}: labelled {report.labelled:,} of {report.visited:,} visited "
            f"({report.labelled_decisive:,} decisive); fitted to {report.fitted_states:,} "
            f"({report.fitted_decisive:,} decisive); gauge safe {report.gauge_safe:.3f}, "
            f"balanced {report.gauge_balanced:.3f}; shielded go-to-target success "
            f"{report.shield_success:.3f}, collision {report.shield_collision:.3f}, overrules "
            f"{report.overruled:.1%}; {report.minutes:.1f} min",
            flush=True,
        )
    if args.test_episodes:
        from qnav.lab.doubt import final_test

        test = final_test(world, args.folder, probe_settings, doubt, args.test_episodes)
        _print_final_test(test, args.test_episodes, args.json)
        if args.export:
            _export_judge(
                world=world,
                folder=args.folder,
                probe=probe_settings,
                test=test,
                reports=finished,
                path=args.export,
            )
    return 0


def _export_judge(
    *,
    world: WorldConfig,
    folder: Path,
    probe: ProbeSettings,
    test: FinalTest,
    reports: list[RoundReport],
    path: Path,
) -> None:
    """Write the folder's latest fit as a doom judge file at the final test's threshold."""
    from qnav.lab.doubt import fitted_network
    from qnav.lab.judge import export_judge, judge_contract

    last = reports[-1]
    training = {
        "label_folder": str(folder),
        "rounds": last.round,
        "fitted_states": last.fitted_states,
        "fitted_decisive": last.fitted_decisive,
        "redrawn_from": probe.redrawn_from,
    }
    contract = judge_contract(world, test, training)
    export_judge(fitted_network(world, folder, probe), contract, path)
    print(
        f"wrote {path}: the doom judge of {folder} (round {last.round}), threshold "
        f"{contract.threshold}; run it with `qnav eval --policy FILE --lookahead judge --judge "
        f"{path}` or lookahead.mode = judge in the controller",
        file=sys.stderr,
    )


def _print_final_test(test: FinalTest, episodes: int, as_json: bool) -> None:
    """The label folder's final test: the threshold chosen on validation layouts, and success on
    the test protocol from the truth, the tracker, and noisy scans."""
    from qnav.lab.doubt import TRACKER_TEST_NOISE_M

    if as_json:
        results = {
            name: asdict(value)
            for name, value in test._asdict().items()
            if name not in ("validation", "threshold")
        }
        print(
            json.dumps(
                {
                    "final_test": {
                        "validation": test.validation,
                        "threshold": test.threshold,
                        **results,
                    }
                }
            )
        )
        return
    chosen = ", ".join(f"{t}: {s:.3f}" for t, s in test.validation.items())
    print(
        f"the latest fit shielding go-to-target, {episodes} episodes each: validation success by "
        f"threshold {chosen}; chosen {test.threshold}\n"
        f"  test protocol: {test.half.success:.3f} at 0.5; at {test.threshold}: "
        f"{test.truth.success:.3f} from the truth, {test.tracked.success:.3f} from the onboard "
        f"tracker's estimate, {test.tracked_noisy.success:.3f} with {TRACKER_TEST_NOISE_M} m "
        "range noise"
    )


def _print_shield_test(test: ShieldTest, as_json: bool) -> None:
    """The shield test's three rows: success, collisions, and how often the shield overruled."""
    rows = [
        ("go-to-target alone", test.blind, 0.0),
        ("shielded by the fitted network", test.fitted, test.fitted_overruled),
        ("shielded by the exact labels", test.exact, test.exact_overruled),
    ]
    if test.tracked is not None:
        rows.insert(
            2,
            (
                "shielded by the fitted network on the onboard tracker's estimate",
                test.tracked,
                test.tracked_overruled,
            ),
        )
    if as_json:
        print(
            json.dumps(
                {
                    "shield_test": {
                        label: {
                            "success": result.success,
                            "collision": result.collision,
                            "episodes": result.episodes,
                            "overruled": overruled,
                        }
                        for label, result, overruled in rows
                    }
                }
            )
        )
        return
    print(f"go-to-target on the test protocol, {test.blind.episodes} episodes:")
    for label, result, overruled in rows:
        print(
            f"  {label}: success {result.success:.3f}, collision {result.collision:.3f}, "
            f"overrules {overruled:.1%} of decisions"
        )


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
    from qnav.controller.perception import TrackerSettings
    from qnav.lab.tracking import TrackerCheckSettings, measure_tracker

    tracker: TrackerSettings
    check: TrackerCheckSettings
    tracker, check = _probe_set(args.probe_assignments, TrackerSettings(), TrackerCheckSettings())
    if args.print_config:
        print(config_text(tracker, check), end="")
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
    if args.print_config:
        print(config_text(settings), end="")
        return 0
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
