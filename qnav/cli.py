"""The `qnav` command: one verb per job, each with its own --help.

Handlers are imported only when their verb runs, so `qnav --help` is instant and the onboard
verbs never import the training stack.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import os
import sys
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from qnav import __version__
from qnav.contracts.errors import ConfigError, PolicyFileError, PolicyInputError
from qnav.contracts.health import DEFAULT_MAX_AGE_S
from qnav.contracts.policy_file import WEIGHT_TYPES
from qnav.options import add_print_config
from qnav.training.config import PRESETS

Handler = Callable[[argparse.Namespace], int]


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


def _resolve(target: str) -> Any:
    """The object `module:name`, its module imported now."""
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name)


def _lazy(target: str) -> Handler:
    """A handler `module:function` imported when called; an optional package missing from this
    install is a ConfigError naming the extra that brings it."""

    def run(args: argparse.Namespace) -> int:
        try:
            handler: Handler = _resolve(target)
            return handler(args)
        except ModuleNotFoundError as error:
            package = (error.name or "").split(".")[0]
            extra = next((e for e, names in EXTRA_MODULES.items() if package in names), None)
            if extra is None:
                raise
            raise ConfigError(f"this {_left_out(package, [extra])}") from None

    return run


def _verb(
    group: argparse._SubParsersAction[_Parser], target: str, name: str, **kwargs: Any
) -> _Parser:
    """A verb's parser, run by the handler `module:function` (imported when it runs)."""
    parser = group.add_parser(name, **kwargs)
    parser.set_defaults(handler=_lazy(target))
    return parser


def _flag(parser: argparse._ActionsContainer, name: str, help_text: str) -> None:
    """An option that is off unless given."""
    parser.add_argument(name, action="store_true", help=help_text)


def _repeated(
    parser: argparse._ActionsContainer, name: str, dest: str, metavar: str, help_text: str
) -> None:
    """An option given any number of times, its values collected in order (--set, --grid)."""
    parser.add_argument(
        name, dest=dest, action="append", default=[], metavar=metavar, help=help_text
    )


def _world_options(parser: argparse.ArgumentParser, default: str | None = "walls-inertia") -> None:
    shown = default or "the policy's own, else walls-inertia"
    parser.add_argument(
        "--scenario",
        default=default,
        help=f"scenario name (`qnav scenarios` lists them; default {shown})",
    )
    parser.add_argument(
        "--world-config",
        type=Path,
        metavar="FILE",
        help="TOML file of world settings applied over the scenario (`qnav eval --print-config` "
        "writes one)",
    )
    _repeated(
        parser,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one world setting, e.g. --set obstacles.count=3 (repeatable)",
    )


def _zenoh_options(parser: argparse.ArgumentParser) -> None:
    """--connect/--listen/--namespace, applied over the configuration's [zenoh] table."""
    parser.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="zenoh endpoint to connect to"
    )
    parser.add_argument(
        "--listen", action="append", metavar="ENDPOINT", help="zenoh endpoint to listen on"
    )
    parser.add_argument("--namespace", help="key prefix (as zenoh-bridge-ros2dds's namespace)")


class _Parser(argparse.ArgumentParser):
    """A verb's parser whose help may end with a listing built only when help is asked for
    (`listing`: the settings, read from their dataclasses' docstrings), and whose options
    generated from settings dataclasses (`generated`) are added only when the verb runs or
    shows its help, so `qnav --help` imports no verb's settings."""

    listing: Callable[[], str] | None = None
    generated: list[tuple[str, str, str, frozenset[str]]]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.generated = []

    def _generate(self) -> None:
        from qnav.options import add_settings_options

        for target, prefix, title, skip in self.generated:
            add_settings_options(self, _resolve(target), prefix, title=title, skip=skip)
        self.generated = []

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self._generate()
        return super().parse_known_args(args, namespace)

    def format_help(self) -> str:
        self._generate()
        if self.listing is not None and self.epilog is None:
            self.epilog = self.listing()
        return super().format_help()


def _settings_options(
    parser: _Parser, target: str, title: str, prefix: str = "", skip: Sequence[str] = ()
) -> None:
    """An option per field of the settings dataclass `module:Class` (qnav.options), in a
    group `title`; `skip` names the fields left to hand-written options."""
    parser.generated.append((target, prefix, title, frozenset(skip)))


def _listing(target: str, intro: str) -> Callable[[], str]:
    """The help listing of the settings dataclass `module:Class` (its defaults), after `intro`;
    imported only when help is asked for."""

    def build() -> str:
        from qnav.contracts.settings import to_listing

        return f"{intro}:\n{to_listing(_resolve(target)())}"

    return build


def _with_listing(parser: _Parser, target: str, intro: str) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.listing = _listing(target, intro)


def _lookahead_option(parser: argparse.ArgumentParser, where: str) -> None:
    parser.add_argument(
        "--lookahead",
        choices=["off", "shield", "plan"],
        default="off",
        help=f"{where}the controller's look ahead (lookahead.mode): the obstacle tracker feeds "
        "a forecast; shield keeps the policy's action unless 0.3 of its continuations collide "
        "within 6 s, then takes its best-valued among the least likely to collide; plan takes "
        "the planner's (10 s ahead)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every verb."""
    parser = argparse.ArgumentParser(
        prog="qnav", description="Learn robot navigation in a fast simulator and run it on a car."
    )
    parser.add_argument("--version", action="version", version=f"qnav {__version__}")
    verbs = parser.add_subparsers(dest="verb", metavar="VERB", required=True, parser_class=_Parser)

    lab = verbs.add_parser(
        "lab",
        help="the research tools of lab/: calibrate, diagnose, gauge (`qnav lab TOOL --help`)",
    )
    tools = lab.add_subparsers(dest="tool", metavar="TOOL", required=True, parser_class=_Parser)

    scenarios = _verb(
        verbs, "qnav.verbs.world:scenarios", "scenarios", help="list the built-in scenarios"
    )
    _flag(
        scenarios,
        "--reference",
        "print the reference of every world setting instead (docs/settings.md)",
    )

    evaluate = _verb(
        verbs,
        "qnav.verbs.world:evaluate",
        "eval",
        help="run the paper's test protocol and print success, collision, unfinished",
    )
    _world_options(evaluate, default=None)
    evaluate.add_argument(
        "--agent",
        default="random",
        choices=["random", "goto", "oracle", "dwa", "map"],
        help="without --policy: random (the paper's Random rows), goto (turn to the target "
        "and drive, blind to obstacles), oracle (a planner that knows the obstacles' future: "
        "an upper bound on success; slow); with --barn also dwa (the Dynamic Window Approach "
        "on the lidar, no map) and map (a planner given the map: an upper bound)",
    )
    evaluate.add_argument(
        "--barn",
        nargs="?",
        const="",
        metavar="DIR",
        help="BARN's protocol, one run per world, over DIR's world_N.world files (with "
        "path_files/ beside them, as published), or BARN's 300 worlds (committed) without DIR: "
        "success, collision, timeout, BARN's metric and loops, overall and by world",
    )
    evaluate.add_argument(
        "--state-error",
        choices=["exact", "lidar-grade", "tracker", "coarse"],
        help="with --agent oracle: plan on a noisy estimate of the state, as a perceive-then-plan "
        "controller would (errors in lab.oracle.PERCEPTION_LEVELS)",
    )
    _flag(
        evaluate,
        "--tracker",
        "with --agent oracle: plan on the onboard obstacle tracker's estimate "
        "(controller.perception: lidar plus pose, the room's walls known) instead of the truth",
    )
    _lookahead_option(evaluate, "with --policy: ")
    evaluate.add_argument(
        "--range-noise-m",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="with --tracker or --lookahead: Gaussian noise added to the ranges the tracker reads",
    )
    evaluate.add_argument(
        "--policy",
        type=Path,
        metavar="RUN_DIR|FILE.onnx",
        help="a training run folder (torch) or an exported policy file (the onboard runtime); "
        "without it the random agent acts",
    )
    evaluate.add_argument(
        "--backend",
        default="onnxruntime",
        choices=["onnxruntime", "numpy"],
        help="runtime backend for a policy file (default onnxruntime)",
    )
    evaluate.add_argument(
        "--random-action-prob",
        type=float,
        default=0.0,
        metavar="P",
        help="with --policy: take a random action with probability P at each step",
    )
    add_print_config(evaluate, markdown=True)
    _settings_options(evaluate, "qnav.sim.evaluate:EvalSettings", "test protocol")
    _flag(evaluate, "--json", "print one JSON object")

    train = _verb(
        verbs, "qnav.verbs.learn:train", "train", help="train a Q-network (resumes a killed run)"
    )
    _world_options(train)
    train.add_argument(
        "--preset",
        default="fast",
        choices=list(PRESETS),
        help="fast: our schedule for 2 CPU cores (default); paper: the paper's exact schedule; "
        "dagger: imitation of the planner given the map (worlds of layouts: the clutter scenario)",
    )
    train.add_argument(
        "--train-config", type=Path, metavar="FILE", help="TOML file with a [train] table"
    )
    _repeated(
        train,
        "--train-set",
        "train_assignments",
        "train.FIELD=VALUE",
        "change one learner setting (repeatable; as its option below)",
    )
    _settings_options(
        train,
        "qnav.training.config:TrainSettings",
        "learner settings (each over the preset, --train-config and --train-set)",
    )
    train.add_argument("--run-dir", type=Path, help="run folder (default runs/SCENARIO/...)")
    _flag(train, "--quiet", "no progress bar")
    add_print_config(train)

    export = _verb(
        verbs,
        "qnav.verbs.learn:export",
        "export",
        help="write a run's policy as one ONNX file with its contract, and test it",
    )
    export.add_argument(
        "run",
        type=Path,
        help="training run folder, or a policy file (.onnx, e.g. of the earlier "
        "qnav-policy/1 layout) to export again in this layout from its own weights",
    )
    export.add_argument(
        "-o", "--output", type=Path, default=None, help="policy file (default RUN/policy.onnx)"
    )
    export.add_argument(
        "--eval-episodes",
        type=int,
        default=None,
        help="test-protocol episodes run on the exported file and recorded in it (0: none; "
        "default 200 for a run or a change of --weights, else 0 for a policy file, whose "
        "recorded results are kept)",
    )
    export.add_argument(
        "--weights",
        choices=WEIGHT_TYPES,
        default=None,
        help="how the large weights are stored: float32, or int8 (a quarter of the bytes, "
        "quicker decisions; its test records how often it agrees with float32). Default: "
        "float32 for a run, the file's own for a policy file",
    )
    _flag(export, "--quiet", "no progress bar")

    calibrate = _verb(
        tools,
        "qnav.verbs.lab:calibrate",
        "calibrate",
        help="random, go-to-target and oracle agents in the paper's scenarios, beside its rows",
    )
    calibrate.add_argument(
        "--episodes", type=int, default=2000, help="random and go-to-target episodes (2000)"
    )
    calibrate.add_argument(
        "--oracle-episodes",
        type=int,
        default=1000,
        help="oracle episodes per obstacle scenario (1000; about 4 CPU-minutes each)",
    )
    calibrate.add_argument("--seed", type=int, default=2024, help="seed of the test layouts")
    _flag(calibrate, "--json", "print one JSON object")

    convert = _verb(
        verbs,
        "qnav.verbs.barn:convert",
        "barn-convert",
        help="write a folder of BARN-format worlds as one compact file (sim/data/barn.npz)",
    )
    convert.add_argument("folder", type=Path, help="folder of world_N.world and path_files/")
    convert.add_argument("-o", "--out", type=Path, required=True, help="the .npz to write")
    convert.add_argument("--name", default="", help="the worlds' name in reports (the folder's)")
    convert.add_argument("--source", required=True, help="where the worlds come from (a URL)")
    convert.add_argument("--commit", required=True, help="the source's commit")
    convert.add_argument("--licence", required=True, help="the worlds' licence")

    render = _verb(
        verbs, "qnav.verbs.world:render", "render", help="draw an episode to PNG and animated GIF"
    )
    _world_options(render, "obstacles-inertia")
    render.add_argument("--agent", default="random", choices=["random"], help="who acts")
    render.add_argument("--seed", type=int, default=0, help="world seed (default 0)")
    render.add_argument("--episode", type=int, default=0, help="episode index of that seed")
    render.add_argument("--max-steps", type=int, default=None, help="cut the episode short")
    _flag(render, "--rays", "draw the lidar rays")
    render.add_argument("--out", type=Path, default=Path("out/render"), help="output folder")

    figures = _verb(
        verbs,
        "qnav.verbs.learn:figures",
        "figures",
        help="action maps (paper figure 3) and trajectories (figure 10) of a run",
    )
    figures.add_argument("run", type=Path, help="training run folder")
    figures.add_argument("--out", type=Path, default=Path("docs/img"), help="output folder")

    diagnose = _verb(
        tools,
        "qnav.verbs.lab:diagnose",
        "diagnose",
        help="why a run learns or not: generalisation gap, target sensitivity, action mix, "
        "test layouts against the blind controller, decisive states",
    )
    diagnose.add_argument("run", type=Path, help="training run folder (finished or not)")
    diagnose.add_argument(
        "--fresh-episodes", type=int, default=64, help="fresh episodes to measure on (64)"
    )

    gauge = _verb(
        tools,
        "qnav.verbs.lab:gauge",
        "gauge",
        help="decisive-state gauge: how often a policy avoids a doomed action where it matters",
    )
    _world_options(gauge, "obstacles-inertia")
    gauge.add_argument(
        "runs", nargs="*", type=Path, help="training run folders to score (each in its own world)"
    )
    gauge.add_argument(
        "--episodes", type=int, default=400, help="episodes per driver behind the state set (400)"
    )
    _flag(
        gauge,
        "--ceiling",
        "also score the best choice under each perception error (is doom learnable?)",
    )
    _flag(gauge, "--json", "print one JSON object per line")

    reproduce = _verb(
        verbs,
        "qnav.verbs.learn:reproduce",
        "reproduce",
        help="the paper's whole study, resumable: trains, tests, writes the tables",
    )
    _study_options(reproduce, Path("runs/study"))
    reproduce.add_argument(
        "--results-dir", type=Path, default=Path("results"), help="one JSON per run (committed)"
    )
    reproduce.add_argument(
        "--docs", type=Path, default=Path("docs/results.md"), help="the tables, as Markdown"
    )
    _flag(
        reproduce,
        "--ablation",
        "also run the target re-drawing ablation (none / paper / hindsight) in the chosen "
        "scenarios among walls-increment and obstacles-inertia",
    )
    reproduce.add_argument(
        "--ablation-seeds", default="0", help="comma-separated seeds of the ablation runs (0)"
    )
    _flag(reproduce, "--tables-only", "rewrite the tables from results/, train nothing")

    sweep = _verb(
        verbs,
        "qnav.verbs.learn:sweep",
        "sweep",
        help="train every point of a settings grid (resumable; locally or on Ray)",
    )
    _study_options(sweep, Path("runs/sweep"), scenarios="walls-inertia", models="recurrent",
                   seeds="0")  # fmt: skip
    sweep.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="SECTION.FIELD=V1,V2,...",
        help="one setting and its values, e.g. --grid train.learning_rate=1e-4,3e-4 (repeatable: "
        "every combination is a run; train.* are learner settings, other sections the world's)",
    )
    _repeated(
        sweep,
        "--set",
        "common",
        "SECTION.FIELD=VALUE",
        "a setting of every run, e.g. --set train.episodes=100 (repeatable)",
    )
    sweep.add_argument(
        "--results-dir",
        type=Path,
        default=Path("runs/sweep/results"),
        help="one JSON per run (a run with one is skipped)",
    )

    controller = _verb(
        verbs,
        "qnav.verbs.onboard:controller",
        "controller",
        help="the onboard daemon: scans, poses, targets in over zenoh, motor commands out",
    )
    _with_listing(
        controller,
        "qnav.controller.config:DaemonConfig",
        "settings (--set SECTION.FIELD=VALUE, or in the --config file; defaults below)",
    )
    controller.add_argument(
        "--config", type=Path, metavar="FILE", help="TOML settings (config/controller.toml)"
    )
    controller.add_argument(
        "--policy", type=Path, metavar="FILE.onnx", help="policy file (over controller.policy)"
    )
    _repeated(
        controller,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one setting, e.g. --set controller.trigger=scan (repeatable)",
    )
    add_print_config(controller)

    record = _verb(
        verbs,
        "qnav.recording:record_verb",
        "record",
        help="record the project's zenoh topics to MCAP (ROS 2 profile, CDR)",
    )
    record.add_argument("--config", type=Path, metavar="FILE", help="recorder TOML file")
    record.add_argument("--out", type=Path, help="output folder (default recordings/)")
    record.add_argument(
        "--folder", type=Path, help="write into exactly this folder (no timestamped subfolder)"
    )
    record.add_argument(
        "--duration-s", type=float, default=0.0, help="stop after this long (0: at SIGINT)"
    )
    _zenoh_options(record)

    certs = _verb(
        verbs,
        "qnav.certs:certs_verb",
        "certs",
        help="a test CA and a certificate per identity, for zenoh's mutual TLS",
    )
    certs.add_argument("folder", type=Path, help="where to write them (e.g. certs/)")
    certs.add_argument(
        "--names",
        nargs="+",
        help="identities (default: hub controller bridge recorder sensors operator server)",
    )
    certs.add_argument(
        "--endpoint",
        default="tls/127.0.0.1:7447",
        help="the hub's TLS endpoint written into the zenoh configs (tls/127.0.0.1:7447)",
    )
    _flag(certs, "--print-commands", "print the openssl commands, run nothing")
    _flag(certs, "--force", "replace the certificates and keys already in FOLDER")

    keys = _verb(
        verbs,
        "qnav.serve:keys_verb",
        "keys",
        help="an Ed25519 key pair that signs the policies qnav serve delivers",
    )
    keys.add_argument("folder", type=Path, help="where to write the key pair (e.g. keys/)")
    _flag(keys, "--force", "replace an existing key pair")

    serve = _verb(
        verbs,
        "qnav.serve:serve_verb",
        "serve",
        help="serve exported policies to cars over zenoh, announcing the best (docs/serve.md)",
    )
    serve.add_argument(
        "sources",
        nargs="+",
        type=Path,
        metavar="SOURCE",
        help="policy files (.onnx), or folders searched for them (run folders, runs/)",
    )
    serve.add_argument(
        "--key",
        type=Path,
        required=True,
        metavar="FILE",
        help="the Ed25519 private key that signs announcements (qnav keys DIR)",
    )
    _settings_options(
        serve,
        "qnav.serve:ServeSettings",
        "serving",
        skip=("sources", "private_key", "zenoh"),
    )
    serve.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="a zenoh JSON5 configuration (TLS, access control: qnav certs writes "
        "zenoh-server.json5)",
    )
    _zenoh_options(serve)
    add_print_config(serve)

    recover = _verb(
        verbs,
        "qnav.recording:recover_verb",
        "recover",
        help="make a killed recording whole: every complete message, indexed, with metadata.yaml",
    )
    recover.add_argument(
        "paths", nargs="+", type=Path, help="recording folders or .mcap files (cut or not)"
    )

    playback = _verb(
        verbs,
        "qnav.recording:playback_verb",
        "playback",
        help="publish MCAP recordings back onto zenoh at their recorded timing, or feed them "
        "into the controller's decision step (--into-controller)",
    )
    playback.add_argument("files", type=Path, nargs="+", help="MCAP files or folders of them")
    playback.add_argument("--speed", type=float, default=1.0, help="time factor (2: twice as fast)")
    _zenoh_options(playback)
    replay = playback.add_argument_group(
        "into the controller",
        "no zenoh: the recording's inputs through a fresh controller, on "
        "the recording's clock (docs/recordings.md)",
    )
    _flag(
        replay,
        "--into-controller",
        "feed the recording into the controller's decision step and report its decisions",
    )
    replay.add_argument("--policy", type=Path, metavar="FILE.onnx", help="policy file")
    replay.add_argument(
        "--config", type=Path, metavar="FILE", help="controller TOML (safety, lidar, topics)"
    )
    _repeated(
        replay,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one controller setting, e.g. --set safety.pose_timeout_s=1.0",
    )
    replay.add_argument(
        "--trigger",
        choices=["scan", "period"],
        help="decide on each scan (default, as `qnav stack` runs the daemon) or every period",
    )
    _flag(replay, "--json", "print the decisions as JSON lines")

    _bridge_verbs(verbs)

    sim_car = _verb(
        verbs,
        "qnav.verbs.onboard:sim_car",
        "sim-car",
        help="the simulator as the car: scans and poses out on zenoh, motion in over MAVLink",
    )
    _world_options(sim_car, "walls-increment")
    _settings_options(sim_car, "qnav.simcar.car:SimCarSettings", "sim-car settings")
    add_print_config(sim_car)
    sim_car.add_argument("--log", type=Path, help="write the episodes as JSON lines here")
    _zenoh_options(sim_car)

    stack = _verb(
        verbs,
        "qnav.stack:stack_verb",
        "stack",
        help="the full stack as separate processes (sim-car, controller, bridge, recorder)",
    )
    stack.add_argument("--policy", type=Path, required=True, help="policy file (.onnx)")
    stack.add_argument("--scenario", help="world (default: the policy's training scenario)")
    stack.add_argument("--episodes", type=int, default=20, help="episodes (20)")
    _lookahead_option(stack, "in the controller, and alike in the in-process comparison: ")
    stack.add_argument("--out", type=Path, default=Path("out/stack"), help="output folder")
    _flag(stack, "--no-record", "do not record to MCAP")
    _flag(stack, "--json", "print one JSON object")
    stack.add_argument(
        "--vehicle",
        choices=["sim", "sitl"],
        default="sim",
        help="the car: the MAVLink test vehicle (sim), or ArduPilot Rover SITL driven in GUIDED "
        "with the pose from the autopilot (sitl; loopback-only namespace, `make stack-sitl`)",
    )
    _flag(
        stack,
        "--real-time",
        "the sim-car in real time: the car moves under whatever command it has while the "
        "next is decided (latency and load included); default: lockstep (`sim-car --lockstep`), "
        "the same episodes as in process. --vehicle sitl always runs in real time",
    )
    stack.add_argument(
        "--sitl-binary", type=Path, help="ardurover binary for --vehicle sitl ($ARDUPILOT_SITL)"
    )
    stack.add_argument(
        "--lidar-turn-s",
        type=float,
        default=0.0,
        metavar="S",
        help="a rotating lidar whose turn takes S seconds (0.1: 10 Hz): each beam cast from where "
        "the car and the obstacles were at its own time, sent with LaserScan's time_increment, "
        "and the same lidar in the in-process comparison (the world's lidar_turn_s; lockstep "
        "only; default 0: instantaneous scans)",
    )
    stack.add_argument(
        "--serve-folder",
        type=Path,
        metavar="DIR",
        help="also run `qnav serve DIR` on the stack's zenoh hub; the controller takes its "
        "policies (policy.source = server), --policy being its starting file (docs/serve.md)",
    )
    stack.add_argument(
        "--keys",
        type=Path,
        metavar="DIR",
        help="with --serve-folder: the key pair `qnav keys DIR` made (the server signs with its "
        "private key, the controller trusts its public key)",
    )

    health = _verb(
        verbs,
        "qnav.verbs.onboard:health",
        "health",
        help="exit 0 while a daemon's loop beats (its QNAV_HEALTH_FILE is fresh): the image's "
        "HEALTHCHECK",
    )
    health.add_argument(
        "--file", type=Path, metavar="PATH", help="health file (default: $QNAV_HEALTH_FILE)"
    )
    health.add_argument(
        "--max-age-s",
        type=float,
        default=DEFAULT_MAX_AGE_S,
        help=f"oldest acceptable beat in seconds ({DEFAULT_MAX_AGE_S:g})",
    )

    bench = verbs.add_parser("bench", help="benchmarks")
    benches = bench.add_subparsers(dest="bench", metavar="WHAT", required=True)
    bench_sim = _verb(
        benches,
        "qnav.verbs.bench:bench_sim",
        "sim",
        help="simulator env-steps per second on one core",
    )
    _world_options(bench_sim, "obstacles-inertia")
    bench_sim.add_argument(
        "--batches", default="1,16,64,256", help="comma-separated batch sizes (1,16,64,256)"
    )
    bench_sim.add_argument(
        "--seconds", type=float, default=2.0, help="timed seconds per configuration (2)"
    )
    _flag(bench_sim, "--no-scaling", "skip beam/obstacle scaling")
    _flag(
        bench_sim,
        "--barn",
        "in BARN's worlds (the barn scenario, each world of the batch in a layout of its own), "
        "driven by random actions and by the planner given the map",
    )
    _flag(bench_sim, "--json", "print one JSON object")
    bench_learner = _verb(
        benches,
        "qnav.verbs.bench:bench_learner",
        "learner",
        help="one training iteration's GFLOP/s against the machine's matmul rate",
    )
    bench_learner.add_argument(
        "--model", default="recurrent", choices=["recurrent", "feedforward"], help="Q-network"
    )
    bench_learner.add_argument("--batch", type=int, default=256, help="batch size (256)")
    bench_learner.add_argument("--repeats", type=int, default=10, help="timed iterations (10)")
    bench_learner.add_argument("--threads", type=int, default=2, help="torch threads (2)")
    _flag(bench_learner, "--json", "print one JSON object")
    bench_policy = _verb(
        benches,
        "qnav.verbs.bench:bench_policy",
        "policy",
        help="per-decision latency of the onboard runtime, per backend, one thread",
    )
    _bench_policy_file(bench_policy)
    bench_policy.add_argument(
        "--backends", default="onnxruntime,numpy", help="comma-separated (onnxruntime,numpy)"
    )
    bench_policy.add_argument(
        "--decisions", type=int, default=3000, help="timed decisions per backend (3000)"
    )
    bench_policy.add_argument(
        "--gap-ms",
        type=float,
        default=0.0,
        help="sleep before each timed decision, as a daemon waits between scans (0: back to "
        "back, caches warm; 20 or 200: the 50 Hz or 5 Hz case)",
    )
    _flag(bench_policy, "--json", "print one JSON object")
    bench_lookahead = _verb(
        benches,
        "qnav.verbs.bench:bench_lookahead",
        "lookahead",
        help="the controller's look ahead per decision: tracker update, shield forecast, plan",
    )
    _world_options(bench_lookahead, "obstacles-inertia")
    bench_lookahead.add_argument(
        "--decisions", type=int, default=2000, help="timed decisions (2000)"
    )
    bench_lookahead.add_argument(
        "--cars",
        type=int,
        default=20,
        help="cars driven side by side, each timed alone and all forecast at once (20)",
    )
    _flag(bench_lookahead, "--json", "print one JSON object")
    bench_controller = _verb(
        benches,
        "qnav.verbs.bench:bench_controller",
        "controller",
        help="end to end: scan published by one process to command received by another",
    )
    _bench_policy_file(bench_controller)
    bench_controller.add_argument(
        "--rates",
        help="comma-separated scan rates in Hz (5,50; with --lookahead, the policy's own rate: "
        "the look ahead decides on every scan)",
    )
    bench_controller.add_argument(
        "--seconds", type=float, default=30.0, help="timed seconds per rate (30)"
    )
    _lookahead_option(bench_controller, "in the daemon, on a drive through the simulated room: ")
    bench_controller.add_argument(
        "--cpu", type=int, metavar="N", help="pin the daemon to core N (default: not pinned)"
    )
    _flag(bench_controller, "--json", "print one JSON object")
    bench_cluster = _verb(
        benches,
        "qnav.verbs.bench:bench_cluster",
        "cluster",
        help="a small fixed study on 1 Ray worker, then on 2: wall times and ratio",
    )
    bench_cluster.add_argument("--repeats", type=int, default=3, help="timed pairs (3)")
    _flag(bench_cluster, "--json", "print one JSON object")
    _bench_bridge(benches)
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


def _mark_extras(verbs: argparse._SubParsersAction[_Parser], prefix: str) -> None:
    """Each verb's help line ends with the extras it needs that this install lacks."""
    for action in verbs._choices_actions:
        missing = missing_extras(prefix + action.dest)
        if missing:
            action.help = f"{action.help} (needs {_needs(missing)})"


def _list_verbs(
    parser: argparse.ArgumentParser, verbs: argparse._SubParsersAction[_Parser]
) -> None:
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


def _study_options(
    parser: _Parser,
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
    _settings_options(
        parser,
        "qnav.training.cluster:ClusterSettings",
        "Ray settings (with --engine ray)",
    )


def _bench_policy_file(bench: argparse.ArgumentParser) -> None:
    """The policy a latency bench times: a file, or the paper-sized one in either weight type."""
    policy = bench.add_mutually_exclusive_group()
    policy.add_argument(
        "--policy",
        type=Path,
        default=None,
        help="policy file (default: an untrained paper-sized recurrent policy, exported here)",
    )
    policy.add_argument(
        "--weights",
        choices=WEIGHT_TYPES,
        default="float32",
        help="weights of the default paper-sized policy: float32 or int8 (float32)",
    )


def _bridge_verbs(verbs: argparse._SubParsersAction[_Parser]) -> None:
    """`qnav bridge` (zenoh to MAVLink) and `qnav fake-vehicle` (a MAVLink car for tests)."""
    bridge = _verb(
        verbs,
        "qnav.verbs.onboard:bridge",
        "bridge",
        help="the firmware bridge: commands from zenoh to the car over MAVLink",
    )
    _with_listing(
        bridge,
        "qnav.firmware_bridge.settings:BridgeSettings",
        "settings (--set SECTION.FIELD=VALUE, or in the --config file; defaults below)",
    )
    bridge.add_argument(
        "--config", type=Path, metavar="FILE", help="TOML settings (see config/bridge.toml)"
    )
    _repeated(
        bridge,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one setting, e.g. --set mavlink.connection=udpin:0.0.0.0:14550",
    )
    add_print_config(bridge)
    bridge.add_argument(
        "--log-level", default="info", choices=["debug", "info", "warning"], help="(info)"
    )

    calibrate_car = _verb(
        verbs,
        "qnav.verbs.onboard:calibrate_car",
        "calibrate-car",
        help="drive a short bounded pattern through a running bridge and fit its speed and "
        "turn-rate scales from the vehicle's own velocity (the car must be armed, and watched)",
    )
    calibrate_car.add_argument(
        "--config", type=Path, metavar="FILE", help="the bridge's TOML settings (its zenoh)"
    )
    _repeated(
        calibrate_car,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        "change one bridge setting (as `qnav bridge --set`)",
    )
    calibrate_car.add_argument(
        "--max-distance-m", type=float, default=15.0, help="abort beyond this (15 m)"
    )
    calibrate_car.add_argument(
        "--wait-s", type=float, default=60.0, help="wait this long for an armed car (60 s)"
    )
    _flag(calibrate_car, "--json", "print one JSON object")
    _flag(
        calibrate_car,
        "--write",
        "write the measured scales into the --config file's [output] section (restart the "
        "bridge to drive with them; until then it assumes a fast car)",
    )

    vehicle = _verb(
        verbs,
        "qnav.verbs.onboard:fake_vehicle",
        "fake-vehicle",
        help="a small MAVLink car that behaves like ArduPilot Rover",
    )
    _with_listing(
        vehicle,
        "qnav.simcar.mavlink_vehicle:MavlinkVehicleSettings",
        "settings (--set FIELD=VALUE, or in the --config file; defaults below)",
    )
    vehicle.add_argument(
        "--config", type=Path, metavar="FILE", help="TOML file of vehicle settings"
    )
    vehicle.add_argument(
        "--connection",
        help="MAVLink connection string (default udpout:127.0.0.1:14550, to the bridge)",
    )
    vehicle.add_argument(
        "--signing-key-file", metavar="FILE", help="sign, and accept only signed messages"
    )
    _repeated(
        vehicle,
        "--set",
        "assignments",
        "FIELD=VALUE",
        "change one setting, e.g. --set dynamics.max_speed_mps=1.0 (repeatable)",
    )
    vehicle.add_argument(
        "--pose-period-s", type=float, default=1.0, help="log the pose this often (0: never)"
    )
    add_print_config(vehicle)
    vehicle.add_argument(
        "--log-level", default="info", choices=["debug", "info", "warning"], help="(info)"
    )


def _bench_bridge(benches: argparse._SubParsersAction[_Parser]) -> None:
    bench = _verb(
        benches,
        "qnav.verbs.bench:bench_bridge",
        "bridge",
        help="command on zenoh to MAVLink on the wire, and the failsafe stop's delay",
    )
    bench.add_argument("--commands", type=int, default=1000, help="timed commands (1000)")
    bench.add_argument(
        "--output", default="manual", choices=["manual", "guided"], help="output mode (manual)"
    )
    bench.add_argument(
        "--timeout-s", type=float, default=0.5, help="failsafe.command_timeout_s (0.5)"
    )
    bench.add_argument("--stops", type=int, default=5, help="failsafe stops timed (5)")
    _flag(
        bench,
        "--baseline",
        "also time a bare zenoh-to-UDP echo process: the floor this machine sets",
    )
    _flag(bench, "--json", "print one JSON object")


ZENOH_DAEMONS = frozenset(
    {"bridge", "calibrate-car", "controller", "playback", "record", "serve", "sim-car"}
)
"""Verbs that run a zenoh session until a signal stops them (or their work is done)."""


def verb_of(args: argparse.Namespace) -> str:
    """The verb as typed: `train`, `lab gauge`, `bench learner`."""
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
