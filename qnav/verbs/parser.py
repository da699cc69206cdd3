"""What a verb's parser is built from: each module of qnav.verbs (and the shell's other verb
modules) defines its verbs' options beside their handlers with these, and `qnav.cli` puts them
together. Only argparse at import: settings dataclasses are read when a verb runs or shows its
help, so `qnav --help` imports none of them."""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeAlias

Handler = Callable[[argparse.Namespace], int]
"""What runs a verb: its parsed options in, its exit status out."""


def resolve(target: str) -> Any:
    """The object `module:name`, its module imported now."""
    module, name = target.split(":")
    return getattr(importlib.import_module(module), name)


class Parser(argparse.ArgumentParser):
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
            add_settings_options(self, resolve(target), prefix, title=title, skip=skip)
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


Verbs: TypeAlias = "argparse._SubParsersAction[Parser]"
"""A group of verbs (`qnav VERB`, `qnav lab TOOL`, `qnav bench WHAT`)."""


def verb(group: Verbs, handler: Handler, name: str, **kwargs: Any) -> Parser:
    """A verb's parser, run by `handler`."""
    parser = group.add_parser(name, **kwargs)
    parser.set_defaults(handler=handler)
    return parser


def flag(parser: argparse._ActionsContainer, name: str, help_text: str) -> None:
    """An option that is off unless given."""
    parser.add_argument(name, action="store_true", help=help_text)


def repeated(
    parser: argparse._ActionsContainer, name: str, dest: str, metavar: str, help_text: str
) -> None:
    """An option given any number of times, its values collected in order (--set, --grid)."""
    parser.add_argument(
        name, dest=dest, action="append", default=[], metavar=metavar, help=help_text
    )


def settings_options(
    parser: Parser, target: str, title: str, prefix: str = "", skip: Sequence[str] = ()
) -> None:
    """An option per field of the settings dataclass `module:Class` (qnav.options), in a
    group `title`; `skip` names the fields left to hand-written options."""
    parser.generated.append((target, prefix, title, frozenset(skip)))


def with_listing(parser: Parser, target: str, intro: str) -> None:
    """End the verb's help with the settings dataclass `module:Class`'s listing (its defaults),
    after `intro`; imported only when help is asked for."""

    def build() -> str:
        from qnav.contracts.settings import to_listing

        return f"{intro}:\n{to_listing(resolve(target)())}"

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.listing = build


def set_options(parser: argparse._ActionsContainer, example: str, what: str = "setting") -> None:
    """`--set SECTION.FIELD=VALUE`, repeatable: one setting changed over the file's."""
    repeated(
        parser,
        "--set",
        "assignments",
        "SECTION.FIELD=VALUE",
        f"change one {what}, e.g. --set {example} (repeatable)",
    )


def world_options(parser: argparse.ArgumentParser, default: str | None = "walls-inertia") -> None:
    """The world a verb runs in: a scenario, a TOML file over it, single settings over both."""
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
    set_options(parser, "obstacles.count=3", "world setting")


def zenoh_options(parser: argparse.ArgumentParser) -> None:
    """--connect/--listen/--namespace, applied over the configuration's [zenoh] table."""
    parser.add_argument(
        "--connect", action="append", metavar="ENDPOINT", help="zenoh endpoint to connect to"
    )
    parser.add_argument(
        "--listen", action="append", metavar="ENDPOINT", help="zenoh endpoint to listen on"
    )
    parser.add_argument("--namespace", help="key prefix (as zenoh-bridge-ros2dds's namespace)")


def lookahead_option(parser: argparse.ArgumentParser, where: str) -> None:
    """`--lookahead off|shield|plan`: the controller's look ahead beside the policy."""
    parser.add_argument(
        "--lookahead",
        choices=["off", "shield", "plan"],
        default="off",
        help=f"{where}the controller's look ahead (lookahead.mode): the obstacle tracker feeds "
        "a forecast; shield keeps the policy's action unless 0.3 of its continuations collide "
        "within 6 s, then takes its best-valued among the least likely to collide; plan takes "
        "the planner's (10 s ahead)",
    )
