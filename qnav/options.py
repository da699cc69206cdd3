"""Command-line options generated from settings dataclasses: one option per field, its help the
field's docstring, so a setting is declared once (in its dataclass) and every verb that takes
it spells it alike.

An option the user did not give is absent from the parsed namespace (argparse.SUPPRESS), so
only the options given override the preset, scenario or configuration file underneath.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from typing import Any, TypeVar

from qnav.contracts.settings import (
    field_docs,
    parse_assignments,
    to_markdown,
    to_toml,
    with_overrides,
)

T = TypeVar("T")

DEST = "setting:"
"""Namespace attribute prefix of a generated option: `setting:train.learning_rate`."""


def add_settings_options(
    parser: argparse.ArgumentParser,
    cls: type,
    prefix: str = "",
    *,
    title: str | None = None,
    skip: frozenset[str] = frozenset(),
) -> None:
    """One `--PREFIX-FIELD` option per field of the frozen dataclass `cls` (nested dataclasses
    give `--PREFIX-SECTION-FIELD`, in a group of their own described by the field's docstring),
    in a group `title`, its help the field's docstring.

    `skip` names fields (dotted for nested ones) left to hand-written options."""
    group = parser.add_argument_group(title) if title else parser
    _add_fields(parser, group, cls, prefix, path="", skip=skip)


def _add_fields(
    parser: argparse.ArgumentParser,
    group: argparse._ActionsContainer,
    cls: type,
    prefix: str,
    *,
    path: str,
    skip: frozenset[str],
) -> None:
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        if not field.init:
            continue
        dotted = f"{path}{field.name}"
        if dotted in skip:
            continue
        annotation = hints[field.name]
        if dataclasses.is_dataclass(annotation) and isinstance(annotation, type):
            section = parser.add_argument_group(dotted, docs.get(field.name, "").replace("%", "%%"))
            _add_fields(parser, section, annotation, prefix, path=f"{dotted}.", skip=skip)
            continue
        flag = "--" + f"{prefix}{dotted}".replace("_", "-").replace(".", "-")
        help_text = docs.get(field.name, "").replace("%", "%%")
        dest = f"{DEST}{prefix}{dotted}"
        if annotation is bool:
            group.add_argument(
                flag,
                dest=dest,
                action=argparse.BooleanOptionalAction,
                default=argparse.SUPPRESS,
                help=help_text,
            )
        else:
            group.add_argument(
                flag,
                dest=dest,
                default=argparse.SUPPRESS,
                metavar=_metavar(annotation),
                help=help_text,
            )


def _metavar(annotation: Any) -> str:
    """What an option takes, as --help shows it: the choices of a Literal, else the type."""
    origin = typing.get_origin(annotation)
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if origin is typing.Literal:
        return "{" + ",".join(str(a) for a in args) + "}"
    if origin in (typing.Union, types.UnionType) and len(args) == 1:
        return _metavar(args[0]) + "|none"
    if origin is tuple:
        return "A,B,..."
    return getattr(annotation, "__name__", "VALUE").upper()


def given_settings(args: argparse.Namespace, prefix: str = "") -> dict[str, Any]:
    """The generated options of `prefix` the user gave, as a nested dict of their values."""
    start = f"{DEST}{prefix}"
    nested: dict[str, Any] = {}
    for key, value in sorted(vars(args).items()):
        if not key.startswith(start):
            continue
        node = nested
        parts = key[len(start) :].split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return nested


def settings_from_args(
    base: T, args: argparse.Namespace, prefix: str = "", assignments: list[str] | None = None
) -> T:
    """`base` with the `SECTION.FIELD=VALUE` assignments of its section (--set spellings), then
    the generated options given, applied; a value that does not fit is a ConfigError naming
    the setting (`train.learning_rate`)."""
    section = getattr(base, "SECTION", "")
    if assignments:
        base = with_overrides(base, parse_assignments(assignments).get(section, {}), section)
    given = given_settings(args, prefix)
    return with_overrides(base, given, section) if given else base


def add_print_config(parser: argparse.ArgumentParser, markdown: bool = False) -> None:
    """`--print-config`, the one spelling of "show me the settings" (and `--markdown`)."""
    parser.add_argument(
        "--print-config",
        action="store_true",
        help="print the settings this command would run with, as a commented TOML file, and exit",
    )
    if markdown:
        parser.add_argument(
            "--markdown",
            action="store_true",
            help="with --print-config: a Markdown table (setting, value, meaning) instead",
        )


def config_text(*settings: object, markdown: bool = False) -> str:
    """What `--print-config` prints: each settings object as commented TOML, one with a
    `SECTION` under its own table (`[train]`), or as Markdown tables."""
    if markdown:
        return "\n".join(to_markdown(each) for each in settings)
    return "\n".join(to_toml(each, getattr(each, "SECTION", "")) for each in settings)
