"""Policy specs: a policy name, optionally with parameters of a rule's config by field name.

    acc-lc                           ACC-LC's defaults
    acc-lc:T=1.0,speed_factor=1.0    ACC-LC with two fields changed (any AccLcConfig field)
    acc-lc-tuned                     the tuned ACC-LC of the scenario family (agents.rules.tuned)
    follower-stopper:window=20       a SternConfig field of Stern et al.'s controllers

A spec is parsed once, before any episode, and every error names the field or value at fault.
Its canonical text (``str(spec)``: fields in their config's order, floats as Python prints them)
is the policy name records and tables carry, so ``T=1`` and ``T=1.0`` are one cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from difflib import get_close_matches
from typing import Any

from agents.rules.acc_lc_config import AccLcConfig
from agents.rules.stern import SternConfig
from mixed_traffic.schema import POLICIES

RULE_CONFIGS: dict[str, type] = {
    "acc-lc": AccLcConfig,
    "acc-lc-conservative": AccLcConfig,
    "acc-lc-tuned": AccLcConfig,
    "follower-stopper": SternConfig,
    "pi-saturation": SternConfig,
}
"""Policies that take parameters, and the config dataclass their fields come from."""
FIXED_FIELDS = ("dt",)
"""Fields a spec may not set: the env gives them (its step length)."""


@dataclass(frozen=True)
class PolicySpec:
    """A parsed policy: ``base`` (a name of ``schema.POLICIES``) and ``params`` (field, value)
    pairs of its rule config, in the config's field order."""

    base: str
    params: tuple[tuple[str, Any], ...] = ()

    def __str__(self) -> str:
        if not self.params:
            return self.base
        return f"{self.base}:" + ",".join(f"{k}={_show(v)}" for k, v in self.params)

    @property
    def overrides(self) -> dict[str, Any]:
        """The parameters as a dict (field -> value)."""
        return dict(self.params)


def parse_policy(text: str) -> PolicySpec:
    """``'acc-lc:T=1.0,speed_factor=1'`` -> PolicySpec; ``ValueError`` (one line) naming an
    unknown policy, an unknown or fixed field, or a value of the wrong type or range."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"policy {text!r} must be a non-empty name such as 'acc-lc'")
    base, _, rest = text.strip().partition(":")
    if base not in POLICIES:
        raise ValueError(f"policy {base!r} is not available; choose from {list(POLICIES)}")
    if not rest:
        if ":" in text:
            raise ValueError(f"policy {text!r}: no parameters after ':' (e.g. {base}:T=1.0)")
        return PolicySpec(base)
    cls = RULE_CONFIGS.get(base)
    if cls is None:
        raise ValueError(f"policy {base!r} takes no parameters (only {', '.join(RULE_CONFIGS)})")
    given = dict(_pair(base, item, cls) for item in rest.split(","))
    order = [f.name for f in fields(cls)]
    params = tuple((k, given[k]) for k in order if k in given)
    build_config(cls, dict(params), base)  # the config's own range checks, now
    return PolicySpec(base, params)


def build_config(cls: type, overrides: dict[str, Any], base: str, start: Any = None) -> Any:
    """``start`` (default ``cls()``) with ``overrides``; a bad value -> ``ValueError``
    prefixed with the policy's name."""
    try:
        return replace(start if start is not None else cls(), **overrides)
    except ValueError as e:
        raise ValueError(f"policy {base!r}: {e}") from None


def _pair(base: str, item: str, cls: type) -> tuple[str, Any]:
    """One ``field=value`` of a spec, the value converted to the field's type."""
    name, eq, raw = (s.strip() for s in item.partition("="))
    known = {f.name: f for f in fields(cls)}
    if not eq or not name:
        raise ValueError(f"policy {base!r}: parameter {item.strip()!r} must read field=value")
    if name in FIXED_FIELDS:
        raise ValueError(f"policy {base!r}: {name!r} is set by the env (its step length)")
    if name not in known:
        close = get_close_matches(name, [n for n in known if n not in FIXED_FIELDS], n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise ValueError(f"policy {base!r}: {name!r} is not a field of {cls.__name__} "
                         f"({cls.__module__}){hint}")  # fmt: skip
    return name, _convert(base, name, raw, getattr(cls(), name))


def _convert(base: str, name: str, raw: str, default: Any) -> Any:
    """``raw`` as the type of the field's ``default`` (bool, int, float or a tuple of floats
    written a/b/c)."""
    try:
        if isinstance(default, bool):
            if raw.lower() not in ("true", "false", "1", "0"):
                raise ValueError
            return raw.lower() in ("true", "1")
        if isinstance(default, tuple):
            value: Any = tuple(float(x) for x in raw.split("/"))
            if len(value) != len(default):
                raise ValueError
        else:
            value = int(raw) if isinstance(default, int) else float(raw)
    except ValueError:
        if isinstance(default, bool):
            want = "true or false"
        elif isinstance(default, tuple):
            want = f"{len(default)} numbers joined by '/'"
        else:
            want = f"a number like {default!r}"
        raise ValueError(f"policy {base!r}: {name}={raw!r} must be {want}") from None
    if not all(math.isfinite(v) for v in (value if isinstance(value, tuple) else [value])):
        raise ValueError(f"policy {base!r}: {name}={raw!r} must be finite")
    return value


def _show(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        return "/".join(repr(float(v)) for v in value)
    return repr(value)
