"""Typed configuration: one dataclass per stage, assembled into named presets.

`paper` uses the paper's sizes (meant for a GPU); `cpu` is small enough to run and train on a
laptop CPU. The resolved config is saved (JSON) beside every output and checkpoint, and
`config_from_dict` rebuilds it, refusing unknown keys, so a run folder can be reproduced.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import Any

from .errors import LookingGlassError
from .hull import HullConfig


@dataclass
class PipelineConfig:
    """Everything `reconstruct` needs. device: "cpu", "cuda", "cuda:1", ... ("auto" = cuda if present)."""

    hull: HullConfig = field(default_factory=HullConfig)
    device: str = "auto"
    seed: int = 0


def _paper() -> PipelineConfig:
    return PipelineConfig(hull=HullConfig(resolution=128))


def _cpu() -> PipelineConfig:
    return PipelineConfig(hull=HullConfig(resolution=128))


PRESETS = {"paper": _paper, "cpu": _cpu}


def preset(name: str) -> PipelineConfig:
    """A fresh copy of a named preset."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise LookingGlassError(f"unknown preset '{name}' (choose from {', '.join(PRESETS)})") from None


def config_to_dict(config: Any) -> dict:
    return dataclasses.asdict(config)


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


def resolve_device(name: str) -> str:
    """'auto' -> 'cuda' when a GPU is present, else 'cpu'; an unavailable CUDA device is an error."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise LookingGlassError(f"device '{name}' requested but CUDA is not available")
    return name
