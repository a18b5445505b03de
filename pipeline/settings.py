"""Typed settings: frozen dataclasses validated once at the boundary and written next to outputs.

A settings class is a frozen dataclass whose fields carry ``metadata={"help": "..."}``; that help
is the CLI's ``--help`` (``add_settings_arguments``).  A class may define ``validate(self)`` that
raises ``UserError``; ``make_settings`` calls it.  ``settings_dict`` gives the JSON form written
beside outputs and used by the freshness check.  ``HelpFormatter`` writes every command's
``--help`` (pipeline.cli): each option's default once, in the option's own syntax.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import textwrap
import typing
import warnings
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
    """A dataclass field with CLI help: ``order: int = setting(8, "SH order of the lighting")``.

    ``help`` says what the setting does; ``--help`` adds its default (HelpFormatter), so the help
    says "(default: ...)" itself only where the default is not a value (e.g. "(default: the sRGB
    curve)" for an empty one).  Metadata ``cli=False`` keeps a field off the command line;
    ``deprecated="what to use instead"`` keeps its option working, hidden from ``--help``, with a
    warning when it is given."""
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata={"help": help, **kwargs})
    return dataclasses.field(default=default, metadata={"help": help, **kwargs})


def memory_limit_setting() -> Any:
    """The ``memory_limit`` field of every stage that streams (linearize, samples, fit): one definition,
    parsed by pipeline.memory (a size, or a share of the machine's RAM)."""
    return setting(
        "50%",
        "peak memory of the stage, its worker processes included: a size (8GB, 512MB, 16GiB) or a "
        "share of the machine's RAM (50%); chunks and workers are chosen to fit, and a capture that "
        "cannot fit is one line saying what to reduce",
    )


def choices_of(cls: type, name: str) -> tuple:
    """The values of field ``name`` of settings class ``cls`` when its type is a Literal (the one
    list of its choices: checked by make_settings, listed by --help), else ()."""
    tp = typing.get_type_hints(cls)[name]
    return typing.get_args(tp) if typing.get_origin(tp) is typing.Literal else ()


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
    for f in dataclasses.fields(cls):  # a choice is a Literal: checked here, once, for every caller
        choices = choices_of(cls, f.name)
        if choices and getattr(obj, f.name) not in choices:
            raise UserError(f"--{f.name.replace('_', '-')} {getattr(obj, f.name)!r}: use one of {', '.join(map(str, choices))}")
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
        return number, None, None  # '1/250' as well as '0.004'
    if tp in (int, str):
        return tp, None, None
    return str, None, None


class _DeprecatedOption(argparse.Action):
    """A setting's option kept for old command lines (``setting(..., deprecated=...)``): it still
    sets the value, says what to use instead, and is hidden from ``--help``."""

    def __init__(self, option_strings, dest, instead: str = "", inner: type[argparse.Action] = argparse._StoreAction, **kwargs):
        self.inner = inner(option_strings, dest, **kwargs)
        self.instead = instead
        super().__init__(
            self.inner.option_strings,
            dest,
            nargs=self.inner.nargs,
            default=kwargs.get("default"),
            type=kwargs.get("type"),
            choices=kwargs.get("choices"),
            help=argparse.SUPPRESS,
        )

    def __call__(self, parser, namespace, values, option_string=None):
        warnings.warn(f"{option_string} is deprecated; {self.instead}", FutureWarning, stacklevel=2)
        self.inner(parser, namespace, values, option_string)

    def format_usage(self) -> str:
        return self.inner.format_usage()


def add_settings_arguments(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one ``--field-name`` option per field of settings dataclass ``cls`` (help from metadata;
    a bool is ``--name / --no-name``; a Literal's values are the option's choices).  The options
    default to SUPPRESS (only what the user gives overrides the settings' defaults); the field's
    default is kept on the option as ``shown_default`` for HelpFormatter."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.metadata.get("cli") is False:
            continue
        tp = hints[f.name]
        flag = "--" + f.name.replace("_", "-")
        help_text = f.metadata.get("help", "").replace("%", "%%")  # argparse expands % in help
        default = (
            f.default
            if f.default is not dataclasses.MISSING
            else (f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        )  # type: ignore[misc]
        if tp is bool:
            kwargs: dict[str, Any] = dict(action=argparse.BooleanOptionalAction)
        else:
            conv, nargs, choices = _cli_type(tp)
            kwargs = dict(type=conv, nargs=nargs, choices=choices)
        if f.metadata.get("deprecated"):
            kwargs = dict(
                kwargs,
                action=_DeprecatedOption,
                instead=f.metadata["deprecated"],
                inner=kwargs.get("action", argparse._StoreAction),
            )
            if tp is bool:
                kwargs = {k: v for k, v in kwargs.items() if k not in ("type", "nargs", "choices")}
        action = parser.add_argument(flag, dest=f.name, default=argparse.SUPPRESS, help=help_text, **kwargs)
        action.shown_default = default


def _default_text(action: argparse.Action) -> str:
    """An option's default as a user would type it, or "" when there is nothing to say: a
    positional or required argument, no value (None, empty), a plain flag (its help says what it
    does); a --name / --no-name pair says which of the two is the default."""
    default = getattr(action, "shown_default", action.default)
    if not action.option_strings or action.required or default is argparse.SUPPRESS or default is None:
        return ""
    if isinstance(action, argparse.BooleanOptionalAction):
        on, off = action.option_strings[0], next(o for o in action.option_strings if o.startswith("--no-"))
        return on if default else off
    if action.nargs == 0:
        return ""
    if isinstance(default, (tuple, list)):
        if not default:
            return ""
        # one token with its own separator (WxH, MIN,MAX), else the values as separate words
        sep = re.fullmatch(r"[A-Z]+([^A-Z]+)[A-Z]+", action.metavar or "") if action.nargs is None else None
        return (sep.group(1) if sep else " ").join(str(v) for v in default)
    return str(default)


class HelpFormatter(argparse.HelpFormatter):
    """Every command's ``--help``: each option's help, then its default once, ``(default: X)``,
    unless the help says its default itself; none for a plain flag (``--force``, ``--no-report``:
    the flag's help says what it does) or an option without a value by default."""

    def _get_help_string(self, action: argparse.Action) -> str:
        help_text = action.help or ""
        if "(default:" in help_text or "%(default)" in help_text:
            return help_text
        shown = _default_text(action)
        return f"{help_text} (default: {shown.replace('%', '%%')})" if shown else help_text

    def _split_lines(self, text: str, width: int) -> list[str]:
        """argparse's wrapping, without breaking a line inside a hyphenated word (--no-rational)."""
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)


def settings_from_args(cls: type[S], args: argparse.Namespace) -> S:
    """Settings from parsed CLI args: only options the user gave override the defaults."""
    names = {f.name for f in dataclasses.fields(cls)}
    values = {k: v for k, v in vars(args).items() if k in names}
    for f in dataclasses.fields(cls):
        if (
            f.name in values
            and isinstance(values[f.name], list)
            and typing.get_origin(typing.get_type_hints(cls)[f.name]) is tuple
        ):
            values[f.name] = tuple(values[f.name])
    return make_settings(cls, **values)
