"""The IoR net's and its trainer's configs (`IorNetConfig`, `IorTrainConfig`), without torch: the
command line builds `train-ior`'s options (and its --help) from them before torch loads. The net
and its training are lookingglass.ior_net.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .configio import check_ranges, setting
from .errors import ConfigError


@dataclass
class IorNetConfig:
    """candidates: the IoRs the hull is rendered at (input channels); bins: the output
    distribution's IoRs (its range is the range the net was trained on); widths: the per-pixel
    mixing's channels and the two strided convolutions'."""

    candidates: list[float] = field(default_factory=lambda: [round(float(c), 4) for c in np.linspace(1.3, 1.7, 9)])
    bin_range: tuple[float, float] = setting((1.3, 1.7), "IoRs of the first and last output bin: the training "
                                             "scenes' range.")
    bins: int = setting(41, "Output bins over bin_range.", range=(2, None))
    widths: list[int] = field(default_factory=lambda: [48, 64, 96])

    def __post_init__(self) -> None:
        check_ranges(self)
        lo, hi = self.bin_range
        if not 1.0 <= lo < hi <= 3.0:
            raise ConfigError(f"bin_range must be LO HI with 1 <= LO < HI <= 3, got {lo} {hi}")

    @property
    def in_channels(self) -> int:
        return 11 + 2 * len(self.candidates)  # image 3, mask 1, N1 3, N2 3, valid 1; per candidate error, valid

    def bin_centres(self):
        """The output bins' IoRs, (bins,) torch tensor."""
        import torch

        return torch.linspace(*self.bin_range, self.bins)


@dataclass
class IorTrainConfig:
    """The IoR net's training (`train-ior`): one scene a step, a random subset of its views. The
    defaults made the shipped weights (800 scenes, ~13 s an epoch on 2 cores)."""

    net: IorNetConfig = field(default_factory=IorNetConfig)
    epochs: int = setting(16, "Passes over the scenes.", range=(1, None))
    lr: float = setting(1e-3, "Initial learning rate.", range=(0, None))
    lr_halve_epochs: int = setting(4, "The learning rate halves every this many epochs.", range=(1, None))
    checkpoint_every: int = setting(200, "Steps between checkpoints.", range=(1, None))
    seed: int = setting(0, "Initialization, shuffling and view-sampling seed.")
    max_scenes: int = setting(0, "Use only the first N scenes (0: all).", range=(0, None))
    min_views: int = setting(5, "Fewest views a step shows the net.", range=(1, None))
    max_views: int = setting(10, "Most views a step shows the net.", range=(1, None))
    photo_noise: float = setting(0.5, "Share of scenes cached as noisy 8-bit photos.", range=(0, 1))
    label_sigma: float = setting(0.01, "Width of the Gaussian target around the true IoR.", range=(0, None))
    init: str = setting("", "Start from these weights.safetensors (same network config).")

    def __post_init__(self) -> None:
        if self.min_views > self.max_views:
            raise ConfigError(f"min_views ({self.min_views}) is above max_views ({self.max_views})")
        check_ranges(self)
