"""Settings machinery shared by every package: range checks that name the setting, overrides
from TOML files or `section.field=value` strings, and field documentation read from the source.

Settings are frozen dataclasses. Each class names its place in a settings file with a class
attribute `SECTION`, and documents each field with the string literal that follows it.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import tomllib
import types
import typing
from pathlib import Path, PurePath
from typing import Any, TypeVar

from qnav.contracts.errors import ConfigError

T = TypeVar("T")


def setting_name(owner: object, field: str) -> str:
    """The dotted name of a field as a user writes it (`obstacles.count`)."""
    section = getattr(owner, "SECTION", "")
    return f"{section}.{field}" if section else field


def check_range(
    owner: object,
    field: str,
    value: float,
    low: float,
    high: float,
    *,
    exclusive_low: bool = False,
    why: str = "",
) -> None:
    """Raise ConfigError naming `owner.field` unless low <= value <= high (or low < value)."""
    ok = (value > low if exclusive_low else value >= low) and value <= high
    if not ok:
        opening = "(" if exclusive_low else "["
        detail = f" ({why})" if why else ""
        raise ConfigError(
            f"{setting_name(owner, field)} = {value!r} is out of range: "
            f"allowed {opening}{low}, {high}]{detail}"
        )


def field_docs(cls: type) -> dict[str, str]:
    """Field name -> the docstring written under it in the class body."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            source = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = ast.parse(source).body[0]
        assert isinstance(body, ast.ClassDef)
        for node, following in zip(body.body, body.body[1:], strict=False):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(following, ast.Expr)
                and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)
            ):
                docs[node.target.id] = " ".join(following.value.value.split())
    return docs


def _coerce(cls: type, name: str, annotation: Any, value: Any, path: str) -> Any:
    """Turn a TOML or command-line value into the field's type, or say what was expected."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if dataclasses.is_dataclass(annotation) and isinstance(annotation, type):
        if not isinstance(value, dict):
            raise ConfigError(f"{path} must be a table of settings, got {value!r}")
        return from_dict(annotation, value, path)
    if origin in (typing.Union, types.UnionType):
        is_none = value is None or (isinstance(value, str) and value.lower() == "none")
        if is_none and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        if isinstance(value, dict) and "kind" in value:
            # Tagged sections (dynamics models): the option whose `kind` matches decides.
            tagged = [a for a in non_none if _kind_of(a) == value["kind"]]
            if not tagged:
                kinds = [_kind_of(a) for a in non_none]
                raise ConfigError(f"{path}.kind = {value['kind']!r}: choose one of {kinds}")
            non_none = tagged
        if len(non_none) == 1:
            return _coerce(cls, name, non_none[0], value, path)
        errors = []
        for option in non_none:
            try:
                return _coerce(cls, name, option, value, path)
            except ConfigError as error:
                errors.append(str(error))
        raise ConfigError(f"{path} = {value!r} fits none of {annotation}: {'; '.join(errors)}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{path} = {value!r} is not allowed: choose one of {list(args)}")
        return value
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.split(",") if v.strip()]
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{path} must be a list, got {value!r}")
        item_type = args[0] if args else Any
        return tuple(_coerce(cls, name, item_type, v, f"{path}[{i}]") for i, v in enumerate(value))
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ConfigError(f"{path} must be true or false, got {value!r}")
    if annotation in (int, float, str):
        if isinstance(value, bool):
            # bool is an int to Python: TOML's `true` would pass as 1, 1.0 or "True".
            raise ConfigError(f"{path} must be {annotation.__name__}, got {value!r}")
        try:
            if annotation is int and isinstance(value, float) and not value.is_integer():
                raise ValueError
            return annotation(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{path} must be {annotation.__name__}, got {value!r}") from None
    return value


def _kind_of(option: Any) -> object:
    fields = (
        {f.name: f for f in dataclasses.fields(option)} if dataclasses.is_dataclass(option) else {}
    )
    return fields["kind"].default if "kind" in fields else None


def from_dict(cls: type[T], values: dict[str, Any], path: str = "") -> T:
    """Build settings `cls` from a nested dict, refusing unknown keys by name."""
    assert dataclasses.is_dataclass(cls)
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        key_path = f"{path}.{key}" if path else key
        if key not in names:
            raise ConfigError(f"unknown setting {key_path!r}: known are {sorted(names)}")
        kwargs[key] = _coerce(cls, key, hints[key], value, key_path)
    return cls(**kwargs)


def to_dict(settings: object) -> dict[str, Any]:
    """Settings as a nested dict of TOML-friendly values."""
    assert dataclasses.is_dataclass(settings) and not isinstance(settings, type)
    out: dict[str, Any] = {}
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out[f.name] = to_dict(value)
        elif isinstance(value, tuple):
            out[f.name] = [to_dict(v) if dataclasses.is_dataclass(v) else v for v in value]
        else:
            out[f.name] = value
    return out


def with_overrides(settings: T, overrides: dict[str, Any], path: str = "") -> T:
    """A copy of `settings` with nested values replaced: {"obstacles": {"count": 3}}; errors
    name a setting under `path` (the section `settings` sits in, if any)."""
    merged = _deep_merge(to_dict(settings), overrides)
    return from_dict(type(settings), merged, path)


def parse_assignments(assignments: list[str]) -> dict[str, Any]:
    """`["obstacles.count=3", "lidar.num_beams=360"]` -> nested dict; values are parsed as TOML."""
    nested: dict[str, Any] = {}
    for item in assignments:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like section.field=value")
        key, raw = item.split("=", 1)
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        node = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return nested


def load_toml(path: Path) -> dict[str, Any]:
    """Read a settings file, saying which file and where if it does not parse."""
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(f"settings file {path} does not exist") from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"settings file {path} is not valid TOML: {error}") from None


def _deep_merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in update.items():
        current = merged.get(key)
        # A section of another `kind` (say, other dynamics) replaces the section whole.
        if (
            isinstance(value, dict)
            and isinstance(current, dict)
            and value.get("kind", current.get("kind")) == current.get("kind")
        ):
            merged[key] = _deep_merge(current, value)
        else:
            merged[key] = value
    return merged


def to_toml(settings: object, section: str = "") -> str:
    """Settings as a TOML document with each field's documentation as a comment above it; with
    `section`, under that table (`[train]`), its nested sections under `[train.NAME]`."""
    return "\n".join(_toml_section(settings, section)).lstrip() + "\n"


def _is_settings(value: object) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def _toml_section(settings: object, prefix: str) -> list[str]:
    docs = field_docs(type(settings))
    lines = [f"[{prefix}]"] if prefix else []
    nested = []
    for f in dataclasses.fields(settings):  # type: ignore[arg-type]
        value = getattr(settings, f.name)
        if _is_settings(value):
            nested.append((f.name, value))
            continue
        if f.name in docs:
            lines.append(f"# {docs[f.name]}")
        if isinstance(value, tuple):
            value = [to_dict(v) if _is_settings(v) else v for v in value]
        lines.append(f"{f.name} = {_toml_value(value)}")
    for name, value in nested:
        lines += ["", *_toml_section(value, f"{prefix}.{name}" if prefix else name)]
    return lines


def _toml_value(value: Any) -> str:
    if value is None:
        return '"none"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, PurePath):
        value = str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"cannot write {value!r} as TOML")


def to_markdown(settings: object) -> str:
    """Settings as a Markdown table: dotted name, value, documentation."""
    rows = ["| setting | value | meaning |", "|---|---|---|"]
    rows += [
        f"| `{name}` | {'(section)' if value is _SECTION else f'`{_toml_value(value)}`'} | {doc} |"
        for name, value, doc in _flatten(settings, "")
    ]
    return "\n".join(rows) + "\n"


def to_listing(settings: object, width: int = 100) -> str:
    """Settings as plain text for a `--help`: each dotted name with its value, then its
    documentation indented below it."""
    lines = []
    for name, value, doc in _flatten(settings, ""):
        shown = "(section)" if value is _SECTION else _toml_value(value)
        lines.append(f"  {name} = {shown}")
        lines += textwrap.wrap(doc, width, initial_indent=" " * 6, subsequent_indent=" " * 6)
    return "\n".join(lines) + "\n"


_SECTION = object()


def _flatten(settings: object, prefix: str) -> list[tuple[str, Any, str]]:
    docs = field_docs(type(settings))
    rows: list[tuple[str, Any, str]] = []
    for f in dataclasses.fields(settings):  # type: ignore[arg-type]
        value = getattr(settings, f.name)
        name = f"{prefix}{f.name}"
        if _is_settings(value):
            rows.append((name, _SECTION, docs.get(f.name, "")))
            rows += _flatten(value, f"{name}.")
        elif isinstance(value, tuple) and value and _is_settings(value[0]):
            rows.append((name, [to_dict(v) for v in value], docs.get(f.name, "")))
        else:
            rows.append((name, value, docs.get(f.name, "")))
    return rows
