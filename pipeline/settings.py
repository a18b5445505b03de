"""Typed settings: frozen dataclasses validated once at the boundary and written next to outputs.

A settings class is a frozen dataclass whose fields carry ``metadata={"help": "..."}``; that help
is the CLI's ``--help`` (``add_settings_arguments``).  A class may define ``validate(self)`` that
raises ``UserError``; ``make_settings`` calls it.  ``settings_dict`` gives the JSON form written
beside outputs and used by the freshness check.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import typing
from pathlib import Path
from typing import Any, TypeVar

from pipeline.errors import UserError

S = TypeVar("S")


def number(text: str) -> float:
    """A number typed by a person: '0.004', '4e-3' or a fraction as cameras print exposure times,
    '1/250'; ValueError otherwise (argparse reports it as "invalid number value")."""
    top, slash, bottom = str(text).strip().partition("/")
    value = float(top)
    if slash:
        divisor = float(bottom)
        value = value / divisor if divisor else float("inf")
    if not math.isfinite(value):
        raise ValueError(f"not a finite number: {text!r}")
    return value



def setting(default: Any, help: str, **kwargs: Any) -> Any:
    """A dataclass field with CLI help: ``order: int = setting(8, "SH order of the lighting")``."""
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata={"help": help, **kwargs})
    return dataclasses.field(default=default, metadata={"help": help, **kwargs})


def _to_jsonable(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (tuple, list)):
        return [_to_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _to_jsonable(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value):
        return settings_dict(value)
    return value


def settings_dict(settings: Any) -> dict:
    """JSON-ready dict of a settings dataclass (paths as strings, tuples as lists)."""
    return {f.name: _to_jsonable(getattr(settings, f.name)) for f in dataclasses.fields(settings)}


def make_settings(cls: type[S], **values: Any) -> S:
    """Build and validate ``cls`` from keyword values; unknown keys or bad values -> UserError."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise UserError(f"unknown setting(s) {', '.join(unknown)} for {cls.__name__}; known: {', '.join(sorted(names))}")
    try:
        obj = cls(**values)
    except (TypeError, ValueError) as exc:
        raise UserError(f"invalid settings for {cls.__name__}: {exc}") from None
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):      # a choice is a Literal: checked here, once, for every caller
        choices = typing.get_args(hints[f.name]) if typing.get_origin(hints[f.name]) is typing.Literal else ()
        if choices and getattr(obj, f.name) not in choices:
            raise UserError(f"--{f.name.replace('_', '-')} {getattr(obj, f.name)!r}: use one of "
                            f"{', '.join(map(str, choices))}")
    validate = getattr(obj, "validate", None)
    if validate is not None:
        validate()
    return obj


def _cli_type(tp: Any):
    """Return (argparse type callable, nargs, choices) for a field annotation."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union:  # Optional[X]
        inner = [a for a in args if a is not type(None)]
        return _cli_type(inner[0]) if len(inner) == 1 else (str, None, None)
    if origin is typing.Literal:
        return type(args[0]), None, list(args)
    if origin in (tuple, list):
        elem = args[0] if args else str
        nargs = "+" if origin is list or (len(args) == 2 and args[1] is Ellipsis) else len(args)
        return number if elem is float else elem, nargs, None
    if tp is Path:
        return Path, None, None
    if tp is float:
        return number, None, None       # '1/250' as well as '0.004'
    if tp in (int, str):
        return tp, None, None
    return str, None, None


def add_settings_arguments(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one ``--field-name`` option per field of settings dataclass ``cls`` (help from metadata)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.metadata.get("cli") is False:
            continue
        tp = hints[f.name]
        flag = "--" + f.name.replace("_", "-")
        help_text = f.metadata.get("help", "").replace("%", "%%")   # argparse expands % in help
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)  # type: ignore[misc]
        if tp is bool:
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction,
                                default=argparse.SUPPRESS, help=f"{help_text} (default: {default})")
            continue
        conv, nargs, choices = _cli_type(tp)
        parser.add_argument(flag, dest=f.name, type=conv, nargs=nargs, choices=choices,
                            default=argparse.SUPPRESS, help=f"{help_text} (default: {default})")


def settings_from_args(cls: type[S], args: argparse.Namespace) -> S:
    """Settings from parsed CLI args: only options the user gave override the defaults."""
    names = {f.name for f in dataclasses.fields(cls)}
    values = {k: v for k, v in vars(args).items() if k in names}
    for f in dataclasses.fields(cls):
        if f.name in values and isinstance(values[f.name], list) and typing.get_origin(typing.get_type_hints(cls)[f.name]) is tuple:
            values[f.name] = tuple(values[f.name])
    return make_settings(cls, **values)
