"""Typed dataclass configs to and from plain dicts (JSON), checking keys and types."""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from .errors import LookingGlassError


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
