"""Checks shared by the validated config dataclasses (``__post_init__``): one message style everywhere.

Every check raises :class:`~guidedmatch.errors.ConfigError` naming the config class, the field, the accepted
values and the value received.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from numbers import Integral, Real

from .errors import ConfigError

__all__ = ["check_number", "check_choice", "check_bool", "config_from", "check_fields"]


def _fail(owner: str, name: str, expected: str, value) -> ConfigError:
    return ConfigError(f"{owner}.{name} must be {expected}; got {value!r}")


def check_number(owner: str, name: str, value, *, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False, hi_open: bool = False, integer: bool = False, allow_none: bool = False):
    """``value`` is a finite (integer) number in the given range (or None when ``allow_none``); returns it."""
    if value is None and allow_none:
        return None
    kind = "an integer" if integer else "a finite number"
    lo_s = "" if lo is None else f"{'>' if lo_open else '>='} {lo:g}"
    hi_s = "" if hi is None else f"{'<' if hi_open else '<='} {hi:g}"
    rng = " and ".join(s for s in (lo_s, hi_s) if s)
    expected = kind + (f" {rng}" if rng else "") + (" or None" if allow_none else "")
    if isinstance(value, bool) or not isinstance(value, Integral if integer else Real):
        raise _fail(owner, name, expected, value)
    if not integer and not math.isfinite(float(value)):
        raise _fail(owner, name, expected, value)
    v = float(value)
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise _fail(owner, name, expected, value)
    if hi is not None and (v >= hi if hi_open else v > hi):
        raise _fail(owner, name, expected, value)
    return value


def check_choice(owner: str, name: str, value, choices: Iterable):
    """``value`` is one of ``choices``; returns it."""
    choices = tuple(choices)
    if value not in choices:
        raise _fail(owner, name, "one of " + ", ".join(repr(c) for c in choices), value)
    return value


def check_bool(owner: str, name: str, value):
    """``value`` is a bool; returns it."""
    if not isinstance(value, bool):
        raise _fail(owner, name, "True or False", value)
    return value


def check_fields(cls, names: Iterable[str]) -> None:
    """Raise a ConfigError listing the valid field names when ``names`` has unknown ones."""
    valid = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(names) - set(valid))
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} option(s): {', '.join(unknown)}; valid: {', '.join(valid)}")


def config_from(cls, value):
    """``None`` -> ``cls()``, an instance -> itself, a mapping -> ``cls(**mapping)`` with unknown names listed."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if isinstance(value, Mapping):
        check_fields(cls, value.keys())
        return cls(**value)
    raise ConfigError(f"config must be a {cls.__name__} or a dict of its fields; got {type(value).__name__}")
