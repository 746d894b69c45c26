"""Typed configuration: one dataclass per stage, assembled into named presets.

`paper` uses the paper's sizes (meant for a GPU); `cpu` is small enough to run and train on a
laptop CPU. The resolved config is saved (JSON) beside every output and checkpoint, and
`config_from_dict` rebuilds it, refusing unknown keys, so a run folder can be reproduced.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .configio import config_from_dict, config_to_dict  # noqa: F401 (re-exported)
from .errors import LookingGlassError
from .hull import HullConfig
from .normals.stage import NormalStageConfig
from .points.stage import SurfaceConfig


@dataclass
class PipelineConfig:
    """Everything `reconstruct` needs. device: "cpu", "cuda", "cuda:1", ... ("auto" = cuda if present)."""

    hull: HullConfig = field(default_factory=HullConfig)
    normals: NormalStageConfig = field(default_factory=NormalStageConfig)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    stop_after: str = "surface"  # visual_hull, normals or surface
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


def resolve_device(name: str) -> str:
    """'auto' -> 'cuda' when a GPU is present, else 'cpu'; an unavailable CUDA device is an error."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise LookingGlassError(f"device '{name}' requested but CUDA is not available")
    return name
