"""The `qnav` command: one verb per job, each with its own --help.

Each verb's options sit beside its handler (the modules of `qnav.verbs`, and `qnav.recording`,
`certs`, `serve` and `stack`, built from `qnav.verbs.parser`); the handlers import what is heavy
only when their verb runs, so `qnav --help` is quick and the onboard verbs never import the
training stack.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import os
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

from qnav import __version__, certs, recording, serve, stack
from qnav.contracts.errors import ConfigError, PolicyFileError, PolicyInputError
from qnav.verbs import barn, learn, onboard, world
from qnav.verbs import bench as bench_verbs
from qnav.verbs import lab as lab_verbs
from qnav.verbs.parser import Parser, Verbs

EXTRA_MODULES = {
    "train": ("torch", "onnx", "onnxscript", "matplotlib"),
    "viz": ("matplotlib", "PIL"),
    "cluster": ("ray",),
    "dev": ("stable_baselines3",),
}
"""The extras of `pyproject.toml` and the packages each brings; the base install is the car's
(no torch, no plotting)."""

VERB_EXTRAS = {
    "train": ("train",),
    "export": ("train",),
    "reproduce": ("train",),
    "sweep": ("train",),
    "figures": ("train",),
    "render": ("viz",),
    "bench learner": ("train",),
    "bench cluster": ("train", "cluster"),
    "lab diagnose": ("train",),
}
"""The verbs that cannot run without an extra: `qnav --help` marks them where it is missing, and
they stop with one line naming it. (A verb that needs one only with some options, such as
`eval --policy RUN`, names it when the import fails.)"""


def missing_extras(verb: str) -> list[str]:
    """The extras `verb` needs that this install lacks (found without importing anything)."""
    return [
        extra
        for extra in VERB_EXTRAS.get(verb, ())
        if any(importlib.util.find_spec(module) is None for module in EXTRA_MODULES[extra])
    ]


def _needs(extras: list[str]) -> str:
    return ", ".join(f"qnav[{extra}]" for extra in extras)


def install_hint(extras: list[str]) -> str:
    """How to add `extras`: pip on the qnav repository, since no package index has qnav;
    editable where this install runs from the checkout itself (`pip install -e .`)."""
    editable = (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file()
    spec = f"'.[{','.join(extras)}]'"
    return f"pip install {'-e ' if editable else ''}{spec} in the qnav repository"


def _left_out(needed: str, extras: list[str]) -> str:
    """The one wording of "this install lacks what that needs, and here is how to get it"."""
    return (
        f"needs {needed}, which this install leaves out (the base install is the car's): "
        f"{install_hint(extras)}"
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every verb: each module of verbs adds its own (their options sit
    beside their handlers)."""
    parser = argparse.ArgumentParser(
        prog="qnav", description="Learn robot navigation in a fast simulator and run it on a car."
    )
    parser.add_argument("--version", action="version", version=f"qnav {__version__}")
    verbs = parser.add_subparsers(dest="verb", metavar="VERB", required=True, parser_class=Parser)
    lab = verbs.add_parser(
        "lab",
        help="the research tools of lab/: calibrate, diagnose, robustness, forecast "
        "(`qnav lab TOOL --help`)",
    )
    tools = lab.add_subparsers(dest="tool", metavar="TOOL", required=True, parser_class=Parser)
    bench = verbs.add_parser("bench", help="benchmarks")
    benches = bench.add_subparsers(dest="bench", metavar="WHAT", required=True)
    for add in (world.add_verbs, learn.add_verbs, barn.add_verbs, onboard.add_verbs):
        add(verbs)
    for add in (recording.add_verbs, certs.add_verbs, serve.add_verbs, stack.add_verbs):
        add(verbs)
    lab_verbs.add_tools(tools)
    bench_verbs.add_benches(benches)
    for prefix, group in (("", verbs), ("lab ", tools), ("bench ", benches)):
        _mark_extras(group, prefix)
    _list_verbs(parser, verbs)
    return parser


VERB_GROUPS = {
    "simulate, learn, test": (
        "scenarios", "eval", "barn-convert", "train", "export", "render", "figures", "reproduce",
        "sweep",
    ),
    "on the car": (
        "controller", "bridge", "calibrate-car", "fake-vehicle", "sim-car", "stack", "record",
        "playback", "recover", "health",
    ),
    "deliver policies": ("serve", "keys", "certs"),
    "measure": ("bench",),
    "research (lab/, apart from the product)": ("lab",),
}  # fmt: skip
"""How `qnav --help` groups the verbs."""


def _mark_extras(verbs: Verbs, prefix: str) -> None:
    """Each verb's help line ends with the extras it needs that this install lacks."""
    for action in verbs._choices_actions:
        missing = missing_extras(prefix + action.dest)
        if missing:
            action.help = f"{action.help} (needs {_needs(missing)})"


def _list_verbs(parser: argparse.ArgumentParser, verbs: Verbs) -> None:
    """`qnav --help` lists the verbs by group (VERB_GROUPS) instead of in one block."""
    helps = {action.dest: action.help or "" for action in verbs._choices_actions}
    grouped = [name for names in VERB_GROUPS.values() for name in names]
    groups = {**VERB_GROUPS, "other": tuple(name for name in helps if name not in grouped)}
    lines: list[str] = []
    for title, names in groups.items():
        if names:
            lines += ["", f"{title}:"] if lines else [f"{title}:"]
            for name in names:
                lines += textwrap.wrap(
                    helps[name],
                    100,
                    initial_indent=f"  {name:<15}",
                    subsequent_indent=" " * 17,
                    break_on_hyphens=False,
                )
    verbs._choices_actions.clear()
    verbs.help = "a verb below; `qnav VERB --help` shows its options"
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = "\n".join(lines)


ZENOH_DAEMONS = frozenset(
    {"bridge", "calibrate-car", "controller", "playback", "record", "serve", "sim-car"}
)
"""Verbs that run a zenoh session until a signal stops them (or their work is done)."""


def verb_of(args: argparse.Namespace) -> str:
    """The verb as typed: `train`, `lab diagnose`, `bench learner`."""
    sub = getattr(args, "tool", None) or getattr(args, "bench", None)
    return f"{args.verb} {sub}" if sub else str(args.verb)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one verb and return its exit status (what tests call in-process)."""
    args = build_parser().parse_args(argv)
    verb = verb_of(args)
    missing = missing_extras(verb)
    if missing:
        print(f"qnav {verb}: {_left_out(_needs(missing), missing)}", file=sys.stderr)
        return 2
    try:
        return int(args.handler(args))
    except (ConfigError, PolicyFileError, PolicyInputError) as error:
        print(f"qnav {verb}: {error}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as error:  # an optional package this install leaves out
        package = (error.name or "").split(".")[0]
        extra = next((e for e, names in EXTRA_MODULES.items() if package in names), None)
        if extra is None:
            raise
        print(f"qnav {verb}: this {_left_out(package, [extra])}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"qnav {verb}: interrupted", file=sys.stderr)
        return 130


def console_main() -> None:
    """Entry point of the `qnav` console command and `python -m qnav`.

    A daemon verb that returned has closed its session, sent its last stop and flushed its
    files; it then leaves without interpreter finalisation. The zenoh runtime's threads outlive
    a closed session; the bridge once aborted after logging "bridge closed" ("FATAL: exception
    not rethrown", exit -6, in a loaded `make test`), most likely such a thread entering Python
    while the interpreter finalised, which unwinds it by force through the binding.
    """
    code = main()
    if len(sys.argv) > 1 and sys.argv[1] in ZENOH_DAEMONS:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    raise SystemExit(code)
