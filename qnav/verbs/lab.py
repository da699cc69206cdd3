"""Handlers of `qnav lab`: the tools of lab/ (calibrate, diagnose, robustness, forecast)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from qnav.contracts.errors import ConfigError
from qnav.verbs.parser import Verbs, flag, verb


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


def robustness(args: argparse.Namespace) -> int:
    """The issue-53 table: each row's world for each column's controller (and, with --forward,
    the always-forward driver under the proximity stop in the realistic room)."""
    from qnav.lab.robustness import COLUMNS, ROWS, forward_collisions, measure, table
    from qnav.sim.config import scenario
    from qnav.sim.evaluate import EvalSettings

    settings = EvalSettings(episodes=args.episodes, seed=args.seed)
    rows = [ROWS[int(i)] for i in args.rows.split(",")] if args.rows else list(ROWS)
    columns = args.columns.split(",") if args.columns else list(COLUMNS)
    if unknown := set(columns) - set(COLUMNS):
        raise ConfigError(f"--columns {sorted(unknown)}: choose from {', '.join(COLUMNS)}")
    results = measure(
        rows, columns, args.policy, settings, room_policy=args.room_policy, progress=True
    )
    print(
        f"{args.episodes} test episodes per cell (seed {args.seed}); policy {args.policy}", end=""
    )
    print(f", in the realistic room {args.room_policy}" if args.room_policy else "")
    print(table(rows, columns, results))
    if args.forward:
        count = forward_collisions(scenario("realistic-room"), settings)
        print(f"always forward under the proximity stop, realistic room: {count}")
    return 0


def forecast(args: argparse.Namespace) -> int:
    """The shield's forecast against the truth over one row of the robustness table."""
    from qnav.lab.forecast_gauge import changed
    from qnav.lab.forecast_gauge import gauge as measure
    from qnav.sim.evaluate import EvalSettings

    world, lookahead, tracker = changed(args.row, args.assignments or [])
    settings = EvalSettings(episodes=args.episodes, seed=args.seed)
    report = measure(world, str(args.policy), settings, lookahead, tracker)
    if args.json:
        print(json.dumps(report))
    else:
        print(", ".join(f"{key} {value:.3f}" for key, value in report.items()))
    return 0


def add_tools(tools: Verbs) -> None:
    """`qnav lab calibrate|diagnose|robustness|forecast`: their options."""
    _add_calibrate(tools)
    _add_diagnose(tools)
    _add_robustness(tools)
    _add_forecast(tools)


def _add_forecast(tools: Verbs) -> None:
    """`qnav lab forecast`."""
    parser = verb(
        tools,
        forecast,
        "forecast",
        help="the shield's forecast against the truth (error over the horizon, coverage, "
        "misses) over a row of the robustness table, in minutes",
    )
    parser.add_argument("--row", type=int, default=0, help="row of `qnav lab robustness` (0)")
    parser.add_argument("--episodes", type=int, default=150, help="test episodes (150)")
    parser.add_argument("--seed", type=int, default=12345, help="seed of the test layouts")
    parser.add_argument(
        "--policy",
        type=Path,
        default=Path("tests/data/stack/obstacles-inertia.onnx"),
        help="policy file (default: the committed obstacles-inertia policy)",
    )
    parser.add_argument(
        "--set",
        dest="assignments",
        action="append",
        metavar="SECTION.FIELD=VALUE",
        help="a lookahead., tracker. or world setting over the row's (repeatable)",
    )
    flag(parser, "--json", "print one JSON object")


def _add_robustness(tools: Verbs) -> None:
    """`qnav lab robustness`."""
    parser = verb(
        tools,
        robustness,
        "robustness",
        help="the controller in rooms that are not the simulator's: blind go-to-target, the "
        "policy alone and as shipped, one change at a time (docs/controller.md)",
    )
    parser.add_argument(
        "--policy",
        type=Path,
        default=Path("tests/data/stack/obstacles-inertia.onnx"),
        help="policy file (default: the committed obstacles-inertia policy)",
    )
    parser.add_argument(
        "--room-policy",
        type=Path,
        help="policy file for the realistic room's row (default --policy)",
    )
    parser.add_argument("--episodes", type=int, default=1000, help="test episodes per cell (1000)")
    parser.add_argument("--seed", type=int, default=12345, help="seed of the test layouts")
    parser.add_argument("--rows", help="comma-separated row numbers (default: all)")
    parser.add_argument("--columns", help="comma-separated: blind, alone, shipped (default: all)")
    flag(parser, "--forward", "also count an always-forward driver's collisions in the room")


def _add_calibrate(tools: Verbs) -> None:
    """`qnav lab calibrate`."""
    parser = verb(
        tools,
        calibrate,
        "calibrate",
        help="random, go-to-target and oracle agents in the paper's scenarios, beside its rows",
    )
    parser.add_argument(
        "--episodes", type=int, default=2000, help="random and go-to-target episodes (2000)"
    )
    parser.add_argument(
        "--oracle-episodes",
        type=int,
        default=1000,
        help="oracle episodes per obstacle scenario (1000; about 4 CPU-minutes each)",
    )
    parser.add_argument("--seed", type=int, default=2024, help="seed of the test layouts")
    flag(parser, "--json", "print one JSON object")


def _add_diagnose(tools: Verbs) -> None:
    """`qnav lab diagnose RUN`."""
    parser = verb(
        tools,
        diagnose,
        "diagnose",
        help="why a run learns or not: generalisation gap, target sensitivity, action mix, "
        "test layouts against the blind controller",
    )
    parser.add_argument("run", type=Path, help="training run folder (finished or not)")
    parser.add_argument(
        "--fresh-episodes", type=int, default=64, help="fresh episodes to measure on (64)"
    )
