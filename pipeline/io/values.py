"""Type checks for values read from JSON and TOML files: a number is an int or a float, never a
bool or a string; a wrong type is a UserError naming where the value came from."""

from __future__ import annotations

from pathlib import PurePath
from typing import Any

import numpy as np

from pipeline.errors import UserError


def is_number(value: Any) -> bool:
    """True for a JSON/TOML number (int or float; not bool, which Python counts as an int)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def number_array(value: Any, where: str, what: str) -> np.ndarray:
    """A number or a (nested, rectangular) list of numbers as a float array; anything else ->
    UserError "{where} must be {what}, got {value!r}"."""

    def numbers_only(v) -> bool:
        return all(numbers_only(x) for x in v) if isinstance(v, list) else is_number(v)

    if numbers_only(value):
        try:
            return np.asarray(value, dtype=float)
        except ValueError:  # ragged lists
            pass
    shown = repr(value) if len(repr(value)) <= 80 else repr(value)[:77] + "..."
    raise UserError(f"{where} must be {what}, got {shown}")


def whole_number(value: Any, where: str, what: str) -> int:
    """A whole number (an int, or a float with no fraction) as int; else UserError as number_array."""
    if not (is_number(value) and np.isfinite(value) and float(value).is_integer()):
        raise UserError(f"{where} must be {what}, got {value!r}")
    return int(value)


def json_ready(obj: Any) -> Any:
    """``obj`` with what JSON cannot hold made plain: arrays -> lists, NumPy scalars -> Python
    numbers, NaN/inf -> None (JSON has no NaN), paths -> strings, keys -> strings."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, PurePath):
        return str(obj)
    return obj
