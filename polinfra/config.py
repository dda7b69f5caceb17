"""Typed, strict configuration loading: TOML → frozen dataclasses.

Every config section is a frozen dataclass whose fields are declared with
:func:`opt`, which carries the field's documentation, unit and allowed range.
:func:`from_dict` builds an instance and rejects unknown keys, wrong types and
out-of-range values with a one-line :class:`~polinfra.errors.ConfigError` that
names the file, the key, the value seen and what is allowed.

Example:
    >>> @dataclasses.dataclass(frozen=True)
    ... class Cam:
    ...     fov_deg: float = opt(50.0, "horizontal field of view", lo=1.0, hi=170.0)
    >>> from_dict(Cam, {"fov_deg": 60}).fov_deg
    60.0
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

from polinfra.errors import ConfigError

__all__ = ["opt", "from_dict", "to_dict", "load_toml", "describe"]

T = TypeVar("T")
_MISSING = dataclasses.MISSING


def opt(
    default: Any = _MISSING,
    doc: str = "",
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    choices: typing.Sequence[Any] | None = None,
    factory: typing.Callable[[], Any] | None = None,
    omit_if_default: bool = False,
) -> Any:
    """Declare a config field with documentation and validation metadata.

    Args:
        default: default value (omit for a required field).
        doc: one-line meaning, with units (shown in errors and ``--help``).
        lo, hi: inclusive numeric bounds (exclusive when ``lo_open`` / ``hi_open``);
            applied to every element of a tuple/list value.
        choices: allowed values (strings and integers, compared exactly).
        factory: default factory for mutable defaults or nested dataclasses.
        omit_if_default: :func:`to_dict` leaves the field out while it holds its default
            (an optional section added later keeps the plain data, and hashes, of
            configs that do not use it unchanged).
    """
    md = {"doc": doc, "lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "choices": choices, "omit_if_default": omit_if_default}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=md)
    return dataclasses.field(default=default, metadata=md)


def load_toml(path: str | os.PathLike) -> dict[str, Any]:
    """Read a TOML file; any syntax error becomes a one-line ConfigError."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        with open(p, "rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: malformed TOML ({exc}); fix the syntax at that line") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not UTF-8 text; save the file as UTF-8 TOML") from None


def _fmt_bounds(md: dict) -> str:
    lo, hi = md.get("lo"), md.get("hi")
    left = "(" if md.get("lo_open") else "["
    right = ")" if md.get("hi_open") else "]"
    return f"{left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"


def _check_range(val: float, md: dict, key: str, where: str) -> None:
    lo, hi = md.get("lo"), md.get("hi")
    if isinstance(val, float) and math.isnan(val):
        raise ConfigError(f"{where}: {key} = nan is not a number; allowed range {_fmt_bounds(md)}")
    bad = False
    if lo is not None and (val < lo or (md.get("lo_open") and val == lo)):
        bad = True
    if hi is not None and (val > hi or (md.get("hi_open") and val == hi)):
        bad = True
    if bad:
        raise ConfigError(f"{where}: {key} = {val} is out of range; allowed {_fmt_bounds(md)} ({md.get('doc', '')})")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(tp: Any, val: Any, key: str, where: str, md: dict) -> Any:
    """Convert a TOML value to the annotated type or raise ConfigError."""
    origin = get_origin(tp)
    args = get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if val is None and type(None) in args:
            return None
        errs = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(a, val, key, where, md)
            except ConfigError as exc:
                errs.append(str(exc))
        raise ConfigError(errs[0] if len(errs) == 1 else f"{where}: {key} = {val!r} has the wrong type; expected {_type_name(tp)}")
    if origin is Literal:
        if val not in args:
            raise ConfigError(f"{where}: {key} = {val!r} is not allowed; choose one of {list(args)}")
        return val
    if dataclasses.is_dataclass(tp):
        if not isinstance(val, dict):
            raise ConfigError(f"{where}: [{key}] must be a table, got {type(val).__name__}")
        return from_dict(tp, val, where=where, prefix=f"{key}.")
    if origin in (tuple, list):
        if not isinstance(val, (list, tuple)):
            raise ConfigError(f"{where}: {key} must be a list, got {val!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(val) != len(args):
                raise ConfigError(f"{where}: {key} must have {len(args)} elements, got {len(val)}")
            out = [_coerce(a, v, f"{key}[{i}]", where, md) for i, (a, v) in enumerate(zip(args, val))]
        else:
            elem = args[0] if args else Any
            out = [_coerce(elem, v, f"{key}[{i}]", where, md) for i, v in enumerate(val)]
        return tuple(out) if origin is tuple else out
    if tp is Any:
        return val
    if tp is float:
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise ConfigError(f"{where}: {key} = {val!r} must be a number")
        val = float(val)
        if not math.isfinite(val):
            raise ConfigError(f"{where}: {key} = {val} must be a finite number")
        _check_range(val, md, key, where)
        return val
    if tp is int:
        if isinstance(val, bool) or not isinstance(val, int):
            raise ConfigError(f"{where}: {key} = {val!r} must be an integer")
        _check_range(val, md, key, where)
        ch = md.get("choices")
        if ch is not None and val not in ch:
            raise ConfigError(f"{where}: {key} = {val!r} is not allowed; choose one of {list(ch)}")
        return val
    if tp is bool:
        if not isinstance(val, bool):
            raise ConfigError(f"{where}: {key} = {val!r} must be true or false")
        return val
    if tp is str:
        if not isinstance(val, str):
            raise ConfigError(f"{where}: {key} = {val!r} must be a string")
        ch = md.get("choices")
        if ch is not None and val not in ch:
            raise ConfigError(f"{where}: {key} = {val!r} is not allowed; choose one of {list(ch)}")
        return val
    raise ConfigError(f"{where}: {key}: unsupported field type {_type_name(tp)}")


def from_dict(cls: type[T], data: dict[str, Any], *, where: str = "config", prefix: str = "") -> T:
    """Build dataclass ``cls`` from a plain dict, strictly.

    Args:
        cls: a dataclass type whose fields were declared with :func:`opt`.
        data: plain data (e.g. from :func:`load_toml`).
        where: the file or context named in error messages.
        prefix: key prefix for nested sections (used in messages).

    Raises:
        ConfigError: unknown key, missing required key, wrong type or out of range.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: section {prefix.rstrip('.') or '<root>'} must be a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key {prefix}{unknown[0]}; accepted keys here: {', '.join(sorted(fields))}")
    kwargs = {}
    for name, f in fields.items():
        key = f"{prefix}{name}"
        if name in data:
            kwargs[name] = _coerce(hints[name], data[name], key, where, dict(f.metadata))
        elif f.default is _MISSING and f.default_factory is _MISSING:
            raise ConfigError(f"{where}: missing required key {key} ({f.metadata.get('doc', '')})")
    try:
        obj = cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {prefix.rstrip('.') or cls.__name__}: {exc}") from None
    return obj


def to_dict(obj: Any) -> Any:
    """Plain-data form of a (nested) config dataclass, fit for TOML/JSON."""
    if dataclasses.is_dataclass(obj):
        return {
            f.name: to_dict(getattr(obj, f.name))
            for f in dataclasses.fields(obj)
            if not (f.metadata.get("omit_if_default") and f.default is not _MISSING and getattr(obj, f.name) == f.default)
        }
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def describe(cls: type) -> list[tuple[str, str, str, str]]:
    """Rows (key, type, default, doc with range) documenting a config dataclass."""
    rows = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        md = dict(f.metadata)
        default = "" if f.default is _MISSING else repr(f.default)
        rng = "" if md.get("lo") is None and md.get("hi") is None else f" range {_fmt_bounds(md)}"
        rows.append((f.name, _type_name(hints[f.name]), default, f"{md.get('doc', '')}{rng}"))
    return rows
