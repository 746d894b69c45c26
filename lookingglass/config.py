"""Typed configuration of `reconstruct`: one dataclass per stage, assembled into PipelineConfig.

The named presets (`cpu`, `paper`) live in lookingglass.presets, with the dataset's and the
trainers' configs. The resolved config is saved (JSON) beside every output and checkpoint, and
`config_from_dict` rebuilds it, refusing unknown keys, so a run folder can be reproduced.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .configio import config_from_dict, config_to_dict, setting  # noqa: F401 (re-exported)
from .errors import ConfigError, LookingGlassError
from .hull import HullConfig
from .normals.stage import NormalStageConfig
from .physics.constants import IOR_MAX, IOR_MIN, check_ior, check_ior_range
from .points.stage import SurfaceConfig
from .refine import RefineConfig


STAGES = ("visual_hull", "normals", "surface", "refine")
IOR_CHOICES = ("scene", "auto")  # the words `ior` takes besides a number


def parse_ior(text: str, name: str = "ior", choices: tuple[str, ...] = IOR_CHOICES) -> str | float:
    """PipelineConfig.ior read: one of `choices` ("scene": scene.json's IoR; "auto": estimated from
    the photos, lookingglass/ior.py) as it is, else the number it holds, in [IOR_MIN, IOR_MAX].
    Raises ConfigError naming `name` and the text."""
    if text in choices:
        return text
    try:
        value = float(text)
    except (TypeError, ValueError):
        words = ", ".join(choices)
        raise ConfigError(f"{name} must be {words} or an index of refraction from {IOR_MIN} to {IOR_MAX}, "
                          f"got {text!r}") from None
    return check_ior(value, name, ConfigError)


@dataclass
class PipelineConfig:
    """Everything `reconstruct` needs. device: "cpu", "cuda", "cuda:1", ... ("auto" = cuda if
    present; resolved once, and every stage, the hull's carving included, runs there).
    stop_after: the last of STAGES to run. ior: `parse_ior`'s text, the IoR every stage assumes
    ("auto": IOR_GLASS moved into ior_range, then estimated from the kept mesh and the photos).
    ior_range: (LO, HI), LO < HI: the range `--ior auto` searches."""

    hull: HullConfig = field(default_factory=HullConfig)
    normals: NormalStageConfig = field(default_factory=NormalStageConfig)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    stop_after: str = setting("refine", f"Last stage to run: {', '.join(STAGES)}.")
    device: str = setting("auto", "cpu, cuda, cuda:N or auto (cuda when present).")
    seed: int = setting(0, "Not read by any stage yet (the point sampling takes surface.seed).")
    ior: str = setting("scene", f"Index of refraction of the object: scene (scene.json's), a number from {IOR_MIN} "
                       f"to {IOR_MAX}, or auto: estimated from the photos at the end (ior_estimate).")
    ior_range: tuple[float, float] = setting((1.3, 1.7), f"LO HI, LO < HI, from {IOR_MIN} to {IOR_MAX}: the indices of "
                                             "refraction searched when ior is auto.")

    def __post_init__(self) -> None:
        if self.stop_after not in STAGES:
            raise ConfigError(f"stop_after must be one of {', '.join(STAGES)}, got {self.stop_after!r}")
        if not (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")):
            raise ConfigError(f"device must be cpu, cuda, cuda:N or auto, got {self.device!r}")
        parse_ior(self.ior)
        check_ior_range(self.ior_range, "ior_range", ConfigError)

    def resolved(self) -> PipelineConfig:
        """This config with its device resolved ("auto" -> what is present) and the hull carving on
        it: what `reconstruct` runs and saves in report.json."""
        import dataclasses

        device = resolve_device(self.device)
        return dataclasses.replace(self, device=device, hull=dataclasses.replace(self.hull, device=device))

    @classmethod
    def from_json(cls, path) -> PipelineConfig:
        """The config of a finished run: its report.json (the "config" entry) or a config JSON."""
        from .fileio import read_json

        data = read_json(path, "config")
        if isinstance(data, dict) and "config" in data:
            data = data["config"]
        try:
            return config_from_dict(cls, data, where=str(path))
        except (TypeError, ValueError) as exc:
            raise LookingGlassError(f"invalid config ({exc})", path) from None


def resolve_device(name: str) -> str:
    """'auto' -> 'cuda' when a GPU is present, else 'cpu'; an unavailable CUDA device is an error."""
    import re

    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name not in ("cpu", "cuda") and not re.fullmatch(r"cuda:\d+", name):
        raise LookingGlassError(f"device must be cpu, cuda, cuda:N or auto, got {name!r}")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise LookingGlassError(f"device '{name}' requested but CUDA is not available")
    if name.startswith("cuda:") and int(name[5:]) >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise LookingGlassError(f"device '{name}' requested but this machine has {count} CUDA device(s): "
                                f"cuda:0 to cuda:{count - 1}")
    return name
