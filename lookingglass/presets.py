"""The named presets, defined once: each holds every config a command starts from.

    cpu    small enough to generate, train and reconstruct on a laptop CPU (the default)
    paper  the paper's sizes and post-processing (meant for a GPU)

A preset is the typed `Preset`: the pipeline's config (`reconstruct`), the dataset's (`generate`),
and the normal and point networks' training configs (`train-normals`, `train-points`); the
networks' own sizes are their modules' `cpu_config` / `paper_config`. The command line builds its
options from these dataclasses and applies what the user gives over the chosen preset.

The shipped weights were trained from `cpu` with per-run overrides (--init, --epochs, --lr,
--lr-halve-epochs, --max-scenes: weights/*.json "provenance", recipes/*.sh), so there is no
separate preset for them.

This module imports the config classes only when a preset is built (they pull in torch), so the
command line can list the names cheaply.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

from .errors import ConfigError

if TYPE_CHECKING:
    from .capture.config import CaptureConfig
    from .config import PipelineConfig
    from .data.dataset import DatasetConfig
    from .ior_net import IorTrainConfig
    from .normals.train import TrainConfig
    from .points.train import PointTrainConfig

DEFAULT_PRESET = "cpu"


@dataclass(frozen=True)
class Preset:
    """Every config of one named preset. pipeline: `reconstruct`; dataset: `generate` (and the
    image size the networks are trained at); normal_training, point_training: the trainers';
    capture: the real-capture commands' (`sfm`, `envmap-from-ball`, `capture`), the same in every
    preset; ior_training: the IoR net's trainer (`train-ior`), the same in every preset."""

    name: str
    pipeline: PipelineConfig
    dataset: DatasetConfig
    normal_training: TrainConfig
    point_training: PointTrainConfig
    capture: CaptureConfig = field(default_factory=lambda: _capture_config())
    ior_training: IorTrainConfig = field(default_factory=lambda: _ior_training_config())


def _capture_config() -> CaptureConfig:
    from .capture.config import CaptureConfig

    return CaptureConfig()


def _ior_training_config() -> IorTrainConfig:
    from .ior_net import IorTrainConfig

    return IorTrainConfig()


def _cpu() -> Preset:
    """Pipeline: the defaults, 10 + 10 latent steps (the angles barely move with more;
    docs/results.md). Dataset: 128 x 96 images (the cpu normal net's size), E 256 x 128, 4 spp --
    about 2.5 s per 10-view scene on one core.

    Normal net: 8 epochs over ~600 scenes, 4 random views a step (more scenes per second than all
    10), a higher rate halved every 3 epochs: ~80 minutes under torchrun on 2 cores (~10 min an
    epoch). The earlier 2 epochs, halved after 1, stopped while the loss still fell: the same data
    for 8 epochs took the test N1 median from 0.88 to 0.73 x the hull's (docs/history.md).

    Point net: the small PNet on 4096 points (points.model.cpu_config, residual start), a higher
    rate (the residual start keeps the first steps tame) halved every 2 of 6 epochs. Measured on a
    2-core machine with another training job on it, 1 thread, 128x96 images, 10 views: feature
    preparation ~4 s a scene (cost volume and normal net ~2.6 s of it), then ~0.33 s a step: for
    600 scenes ~40 min of features once and ~3.5 min an epoch."""
    from .config import PipelineConfig
    from .data.dataset import DatasetConfig
    from .normals import model as normal_model
    from .normals.train import TrainConfig
    from .points import model as point_model
    from .points.train import PointTrainConfig

    return Preset(
        name="cpu",
        pipeline=PipelineConfig(),
        dataset=DatasetConfig(),
        normal_training=TrainConfig(net=normal_model.cpu_config(), epochs=8, lr=4e-4, lr_halve_epochs=3,
                                    views_per_step=4),
        point_training=PointTrainConfig(net=point_model.cpu_config(), epochs=6, lr=3e-4, lr_halve_epochs=2,
                                        checkpoint_every=100),
    )


def _paper() -> Preset:
    """Pipeline: the paper's post-processing, 500 latent-optimization steps on N2, then 500 on
    both (~0.9 s a step for 10 views on this CPU). Dataset: 256 x 192 images (the paper's network
    resolution), E 512 x 256, 9 spp (about the samples of the paper's 480 x 360 4-spp renders
    area-downsampled to 256 x 192). Networks: the paper's; training: 10 epochs at 1e-4, halved
    every 2 (the paper's schedule)."""
    from .config import PipelineConfig
    from .data.dataset import DatasetConfig
    from .normals import model as normal_model
    from .normals.latent import LatentOptConfig
    from .normals.stage import NormalStageConfig
    from .normals.train import TrainConfig
    from .points import model as point_model
    from .points.train import PointTrainConfig

    return Preset(
        name="paper",
        pipeline=PipelineConfig(normals=NormalStageConfig(latent=LatentOptConfig(iterations_n2=500,
                                                                                 iterations_both=500))),
        dataset=DatasetConfig(preset="paper", width=256, height=192, envmap_height=256, samples_per_axis=3),
        normal_training=TrainConfig(net=normal_model.paper_config()),
        point_training=PointTrainConfig(net=point_model.paper_config()),
    )


PRESETS: dict[str, Callable[[], Preset]] = {"cpu": _cpu, "paper": _paper}
PRESET_NAMES = tuple(PRESETS)


def preset(name: str = DEFAULT_PRESET) -> Preset:
    """A fresh copy of the named preset (its configs are the caller's to change)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown preset {name!r} (choose from {', '.join(PRESET_NAMES)})") from None
