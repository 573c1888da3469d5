"""argparse options built from the config dataclasses and their field docstrings.

``add_config_args(parser, EnvConfig, only=["scenario", "density", "sensors.lidar_range"])`` adds
``--scenario``, ``--density``, ``--sensors.lidar-range`` with the field docstring (units
included) as help and the dataclass default shown. ``config_from_args(args, EnvConfig)`` builds
the config from the options that were given, keeping the dataclass defaults for the others; a
``ValueError`` from the config's checks is for the caller to turn into ``parser.error``.

Field types: ``bool`` becomes ``--x/--no-x``; ``tuple[T, ...]`` takes one or more values;
``T | None`` takes a ``T``; ``Path`` a path; anything else is read as text.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mixed_traffic.config import field_docs

_PREFIX = "cfg__"


def _whole_number(text: str) -> int:
    """Integer that also accepts 2e6 and 2_000_000."""
    value = float(text.replace("_", ""))
    if value != int(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number")
    return int(value)


def policy_arg(text: str) -> str:
    """argparse type of a policy option: the canonical spec (``acc-lc:T=1.0``), or the
    one-line error naming what is wrong (:func:`mixed_traffic.experiments.runner.check_policy`)."""
    from mixed_traffic.experiments.runner import check_policy

    try:
        return check_policy(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


_TYPES: dict[str, Any] = {"float": float, "int": _whole_number, "str": str, "Path": Path}


def _fields(cls: type, prefix: str = "") -> list[tuple[str, dataclasses.Field, type]]:
    """(dotted name, field, owning class) of every scalar field, nested dataclasses flattened."""
    out = []
    for f in dataclasses.fields(cls):
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            out += _fields(type(default), f"{prefix}{f.name}.")
        else:
            out.append((f"{prefix}{f.name}", f, cls))
    return out


def _default(f: dataclasses.Field) -> Any:
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


def config_dest(name: str) -> str:
    """argparse ``dest`` of a (dotted) config field: hand-written options that set a field
    (e.g. flags choosing a value) use it, and ``config_from_args`` picks them up."""
    return _PREFIX + name.replace(".", "__")


def _kind(f: dataclasses.Field) -> tuple[str, bool]:
    """(scalar type name, takes several values) of a field's annotation."""
    kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "str")
    kind = kind.removesuffix(" | None")
    if kind.startswith("tuple[") and kind.endswith(", ...]"):
        return kind[len("tuple[") : -len(", ...]")], True
    return kind, False


def add_config_args(
    parser: argparse.ArgumentParser,
    cls: type,
    only: Sequence[str] | None = None,
    defaults: dict[str, Any] | None = None,
    group_title: str | None = None,
) -> None:
    """Add one ``--option`` per (selected) field of dataclass ``cls``.

    Args:
        parser: parser to extend.
        cls: a config dataclass (e.g. ``EnvConfig``); nested dataclass fields are addressed
            with dots (``sensors.lidar_range`` -> ``--sensors.lidar-range``).
        only: dotted field names to expose, in this order (default: every scalar field).
        defaults: CLI defaults that differ from the dataclass's, by dotted name.
        group_title: put the options in an argument group with this title.
    """
    table = {name: (f, owner) for name, f, owner in _fields(cls)}
    names = list(only) if only is not None else list(table)
    unknown = [n for n in names if n not in table]
    if unknown:
        raise KeyError(f"{cls.__name__} has no field(s) {unknown}; known: {sorted(table)}")
    defaults = defaults or {}
    target = parser.add_argument_group(group_title) if group_title else parser
    for name in names:
        f, owner = table[name]
        doc = field_docs(owner).get(f.name, "")
        shown = defaults.get(name, _default(f))
        kind, several = _kind(f)
        option = "--" + name.replace("_", "-")
        dest = config_dest(name)
        if isinstance(shown, tuple):
            shown = " ".join(map(str, shown))
        shown = None if shown == "" else shown  # the docstring says what "unset" means
        help_text = (doc if shown is None else f"{doc} (default: {shown})").replace("%", "%%")
        if kind == "bool":
            target.add_argument(
                option, dest=dest, action=argparse.BooleanOptionalAction, default=None,
                help=help_text,
            )  # fmt: skip
        else:
            target.add_argument(
                option, dest=dest, type=_TYPES.get(kind, str), default=None,
                nargs="+" if several else None, metavar=name.rsplit(".", 1)[-1].upper(),
                help=help_text,
            )  # fmt: skip
        if name in defaults:
            parser.set_defaults(**{dest: defaults[name]})


def config_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """Nested dict of the config options given on the command line (or defaulted by the CLI)."""
    out: dict[str, Any] = {}
    for key, value in vars(args).items():
        if not key.startswith(_PREFIX) or value is None:
            continue
        parts = key[len(_PREFIX) :].split("__")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = tuple(value) if isinstance(value, list) else value
    return out


def config_from_args(args: argparse.Namespace, cls: type, **extra: Any) -> Any:
    """Instance of ``cls`` from the parsed options plus ``extra`` field values.

    Raises:
        ValueError: a value is out of range (message names the field); call ``parser.error``.
    """
    data = config_overrides(args)
    data.update(extra)
    defaults = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():  # cls() itself may be invalid (e.g. a budget is required)
        if isinstance(value, dict):
            value = dataclasses.replace(_default(defaults[key]), **value)
        kwargs[key] = value
    return cls(**kwargs)


def check_table(rows: list[dict[str, Any]]) -> str:
    """A check tool's rows (check, where, value, pass) as aligned text, one per line."""
    head = {"check": "check", "where": "where", "value": "value", "pass": "pass"}
    cells = [head, *({**r, "pass": "yes" if r["pass"] else "NO"} for r in rows)]
    widths = {k: max(len(str(c[k])) for c in cells) for k in head}
    return "\n".join("  ".join(str(c[k]).ljust(widths[k]) for k in head) for c in cells)
