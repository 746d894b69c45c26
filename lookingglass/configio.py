"""Typed dataclass configs to and from plain dicts (JSON), checking keys and types; `setting`: a field
with its help and range, `check_ranges`: the check a config's __post_init__ runs."""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Any

from .errors import ConfigError, LookingGlassError


def config_to_dict(config: Any) -> dict:
    return dataclasses.asdict(config)


def changed_keys(a: dict, b: dict) -> list[str]:
    """The top-level keys whose values differ between two config dicts (either side's), sorted."""
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def config_from_dict(cls: type, data: dict, where: str = "config") -> Any:
    """Build dataclass `cls` from nested dicts, checking keys and basic types."""
    if not isinstance(data, dict):
        raise LookingGlassError(f"{where}: expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise LookingGlassError(f"{where}: unknown key(s) {', '.join(unknown)}")
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint):
            kwargs[name] = config_from_dict(hint, value, f"{where}.{name}")
        else:
            kwargs[name] = _coerce(hint, value, f"{where}.{name}")
    return cls(**kwargs)


def _coerce(hint: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    if origin in (tuple, list):
        return origin(value)
    if hint is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if hint in (int, str, bool) and not isinstance(value, hint):
        raise LookingGlassError(f"{where}: expected {hint.__name__}, got {value!r}")
    return value


def setting(default: Any, help: str = "", range: tuple | None = None, cli_range: tuple | None = None) -> Any:
    """A config field with what the command line shows and checks (dataclasses.field metadata):
    help: its option's help; range (low, high), either None for open: the values the config
    accepts (`check_ranges`, called by the config's __post_init__); cli_range: a narrower range
    the command line takes (a library caller may go outside it, e.g. tests on tiny inputs)."""
    return dataclasses.field(default=default, metadata={"help": help, "range": range, "cli_range": cli_range})


def out_of_range(name: str, value: Any, bounds: tuple | None) -> str | None:
    """'NAME must be in [low, high], got VALUE' when `value` is outside `bounds`, else None."""
    if bounds is None or value is None:
        return None
    if isinstance(value, (tuple, list)):  # a fixed tuple: each element in the range
        return next((p for p in (out_of_range(name, v, bounds) for v in value) if p), None)
    low, high = bounds
    if (low is None or value >= low) and (high is None or value <= high):
        return None
    if high is None:
        return f"{name} must be at least {low}, got {value}"
    if low is None:
        return f"{name} must be at most {high}, got {value}"
    return f"{name} must be in [{low}, {high}], got {value}"


def not_finite(name: str, value: Any) -> str | None:
    """'NAME must be a finite number, got VALUE' when `value` (or an element of a tuple or list) is a
    float that is NaN or infinite, else None: an open range's bound lets inf through, and NaN passes
    every comparison."""
    values = value if isinstance(value, (tuple, list)) else (value,)
    bad = next((v for v in values if isinstance(v, float) and not math.isfinite(v)), None)
    return None if bad is None else f"{name} must be a finite number, got {bad}"


def check_ranges(config: Any) -> None:
    """Raise ConfigError for the first float field of `config` that is not finite, or the first field
    outside its `setting(range=...)`."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        problem = not_finite(f.name, value) or out_of_range(f.name, value, f.metadata.get("range"))
        if problem:
            raise ConfigError(problem)
