"""The named presets, defined once: each holds every config a command starts from.

    cpu    small enough to generate, train and reconstruct on a laptop CPU (the default)
    paper  the paper's sizes and post-processing (meant for a GPU)

A preset is the typed `Preset`: the pipeline's config (`reconstruct`), the dataset's (`generate`),
and the normal and point networks' training configs (`train-normals`, `train-points`); the
networks' own sizes are their config modules' `cpu_config` / `paper_config` (lookingglass.normals.config,
lookingglass.points.config). The command line builds its
options from these dataclasses and applies what the user gives over the chosen preset.

The shipped weights were trained from `cpu` with per-run overrides (--init, --epochs, --lr,
--lr-halve-epochs, --max-scenes: weights/*.json "provenance", recipes/*.sh), so there is no
separate preset for them.

A preset builds each config when it is first read, importing only that config's module; none of
them imports torch (the trainers' configs live in lookingglass.normals.config,
lookingglass.points.config and lookingglass.ior_net_config, apart from the networks), so every
command reads and checks its options, and shows its --help, before torch loads.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

from .errors import ConfigError

if TYPE_CHECKING:
    from .capture.config import CaptureConfig
    from .config import PipelineConfig
    from .data.dataset import DatasetConfig
    from .ior_net_config import IorTrainConfig
    from .normals.config import TrainConfig
    from .points.config import PointTrainConfig

DEFAULT_PRESET = "cpu"


class Preset:
    """Every config of one named preset, each built from its factory when first read. pipeline:
    `reconstruct`; dataset: `generate` (and the image size the networks are trained at);
    normal_training, point_training: the trainers'; capture: the real-capture commands' (`sfm`,
    `envmap-from-ball`, `capture`), the same in every preset; ior_training: the IoR net's trainer
    (`train-ior`), the same in every preset."""

    CONFIGS = ("pipeline", "dataset", "normal_training", "point_training", "capture", "ior_training")
    name: str
    pipeline: PipelineConfig
    dataset: DatasetConfig
    normal_training: TrainConfig
    point_training: PointTrainConfig
    capture: CaptureConfig
    ior_training: IorTrainConfig

    def __init__(self, name: str, **factories: Callable[[], Any]):
        factories = {"capture": _capture_config, "ior_training": _ior_training_config, **factories}
        if set(factories) != set(self.CONFIGS):
            raise TypeError(f"a preset's factories are {self.CONFIGS}, got {tuple(factories)}")
        self.name = name
        self._factories = factories

    def __getattr__(self, config: str) -> Any:
        # only called for what is not built yet (a built config is an instance attribute)
        factories = self.__dict__.get("_factories", {})
        if config not in factories:
            raise AttributeError(f"{type(self).__name__} has no config {config!r}")
        built = self.__dict__[config] = factories[config]()
        return built


def _capture_config() -> CaptureConfig:
    from .capture.config import CaptureConfig

    return CaptureConfig()


def _ior_training_config() -> IorTrainConfig:
    from .ior_net_config import IorTrainConfig

    return IorTrainConfig()


def _cpu() -> Preset:
    """Pipeline: the defaults, no latent-optimization steps (they move the angles by hundredths of a
    degree and the final mesh not at all; `LatentOptConfig`). Dataset: 128 x 96 images (the cpu
    normal net's size), E 256 x 128, 4 spp --
    about 2.5 s per 10-view scene on one core.

    Normal net: 8 epochs over ~600 scenes, 4 random views a step (more scenes per second than all
    10), a higher rate halved every 3 epochs: ~80 minutes under torchrun on 2 cores (~10 min an
    epoch). The earlier 2 epochs, halved after 1, stopped while the loss still fell: the same data
    for 8 epochs took the test N1 median from 0.88 to 0.73 x the hull's (docs/history.md).

    Point net: the small PNet on 4096 points (points.config.cpu_config, residual start), a higher
    rate (the residual start keeps the first steps tame) halved every 2 of 6 epochs. Measured on a
    2-core machine with another training job on it, 1 thread, 128x96 images, 10 views: feature
    preparation ~4 s a scene (cost volume and normal net ~2.6 s of it), then ~0.33 s a step: for
    600 scenes ~40 min of features once and ~3.5 min an epoch."""
    def pipeline() -> PipelineConfig:
        from .config import PipelineConfig

        return PipelineConfig()

    def dataset() -> DatasetConfig:
        from .data.dataset import DatasetConfig

        return DatasetConfig()

    def normal_training() -> TrainConfig:
        from .normals.config import TrainConfig, cpu_config

        return TrainConfig(net=cpu_config(), epochs=8, lr=4e-4, lr_halve_epochs=3, views_per_step=4)

    def point_training() -> PointTrainConfig:
        from .points.config import PointTrainConfig, cpu_config

        return PointTrainConfig(net=cpu_config(), epochs=6, lr=3e-4, lr_halve_epochs=2,
                                checkpoint_every=100)

    return Preset("cpu", pipeline=pipeline, dataset=dataset, normal_training=normal_training,
                  point_training=point_training)


def _paper() -> Preset:
    """Pipeline: the paper's post-processing, 500 latent-optimization steps on N2, then 500 on
    both (~0.9 s a step for 10 views on this CPU). Dataset: 256 x 192 images (the paper's network
    resolution), E 512 x 256, 9 spp (about the samples of the paper's 480 x 360 4-spp renders
    area-downsampled to 256 x 192). Networks: the paper's; training: 10 epochs at 1e-4, halved
    every 2 (the paper's schedule)."""
    def pipeline() -> PipelineConfig:
        from .config import LatentOptConfig, NormalStageConfig, PipelineConfig

        return PipelineConfig(normals=NormalStageConfig(latent=LatentOptConfig(iterations_n2=500, iterations_both=500)))

    def dataset() -> DatasetConfig:
        from .data.dataset import DatasetConfig

        return DatasetConfig(preset="paper", width=256, height=192, envmap_height=256, samples_per_axis=3)

    def normal_training() -> TrainConfig:
        from .normals.config import TrainConfig, paper_config

        return TrainConfig(net=paper_config())

    def point_training() -> PointTrainConfig:
        from .points.config import PointTrainConfig, paper_config

        return PointTrainConfig(net=paper_config())

    return Preset("paper", pipeline=pipeline, dataset=dataset, normal_training=normal_training,
                  point_training=point_training)


PRESETS: dict[str, Callable[[], Preset]] = {"cpu": _cpu, "paper": _paper}
PRESET_NAMES = tuple(PRESETS)


def preset(name: str = DEFAULT_PRESET) -> Preset:
    """A fresh copy of the named preset (its configs are the caller's to change)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown preset {name!r} (choose from {', '.join(PRESET_NAMES)})") from None
