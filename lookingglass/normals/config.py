"""The normal network's and its trainer's configs (`NormalNetConfig`, `TrainConfig`), without
torch: the command line builds `train-normals`' options (and its --help) from them before torch
loads. The network is lookingglass.normals.model, the training lookingglass.normals.train.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from ..configio import check_ranges, setting
from ..errors import ConfigError
from ..physics.constants import IOR_GLASS

# The supplement's cost-volume angles: theta = 0, t, t, t and phi = 0, 0, 120, 240 degrees, with
# t chosen from the visual hull's normal error for each view count.
COST_VOLUME_THETA_DEG = {5: 25.0, 10: 15.0, 20: 10.0}


@dataclass
class NormalNetConfig:
    """Widths of NNet/FNet and the ablation switches. `paper` sizes are the paper's."""

    width: int = setting(256, "Input width (the data's).", range=(8, None))
    height: int = setting(192, "Input height (the data's).", range=(8, None))
    enc_channels: tuple[int, int, int] = setting((64, 256, 512), "Encoder widths, finest first.", range=(1, None))
    fnet_channels: int = setting(64, "FNet (cost-volume feature) width.", range=(1, None))
    groups: int = setting(16, "GroupNorm groups (each width a multiple of them).", range=(1, None))
    use_error_map: bool = setting(True, "Feed the hull normals' rendering error and TIR mask (wr).")
    use_cost_volume: bool = setting(True, "Add the cost volume (wr+cv).")
    num_views: int = setting(10, "Views per scene.", range=(2, None))
    cost_volume_k: int = setting(4, "Candidate normals per interface in the cost volume (K; K x K pairs).",
                                 range=(1, None))
    cost_volume_theta_deg: float | None = setting(None, "Cost-volume angle (degrees; default: the supplement's for "
                                                        "num_views).")
    # Ours, not the paper's: predict a correction to the hull's normals, normalize(Ñ + tanh(out)),
    # with the last layer zero-initialized, so an untrained net starts at the hull's normals and
    # training spends its steps on corrections (the paper's net regresses normals from scratch).
    residual: bool = setting(False, "Predict a correction to the hull's normals (ours), not the normals.")
    # Ours: a head that predicts, per pixel, how many degrees closer to the truth the net's N1 and
    # N2 are than the hull's -- than the input mesh's, whatever mesh the net is fed: the refine
    # stage feeds it its own mesh -- so that later stages can tell where to follow the prediction (the
    # rendering error tells that only weakly, and an estimate of the net's own error alone does not
    # either; docs/history.md). Trained after the normals, on their frozen features.
    gain_head: bool = setting(False, "Also predict, per pixel, how much closer to the truth the predicted N1 and N2 "
                                     "are than the input mesh's (the hull's in training; degrees; ours).")
    # Ours: the decoder's correction comes up from 1/8 resolution with no skip link. This head reads the
    # correction and the inputs at full resolution and adds to the correction (zero-initialized: it
    # starts as the plain net). It sharpens the corrections coarse hulls and smooth shapes need (test
    # split N1 median 7.96 -> 6.56 deg); it was meant to spare the creases of good CAD hulls and does not
    # (docs/results.md, issue 27).
    detail_head: bool = setting(False, "Add a full-resolution head that corrects the decoder's output from the "
                                       "inputs (ours).")

    # Settings that change no parameter: weights trained at one view count can start (--init)
    # training at another -- the cost volume samples K neighbours whatever the rig -- and weights
    # trained at one image size at another (the net is fully convolutional).
    FINE_TUNE_FREE: ClassVar[frozenset] = frozenset({"num_views", "cost_volume_theta_deg", "width", "height"})
    # Weights without the gain head or the detail head may start the training of one
    # (NormalNet.widen_initial_state).
    FINE_TUNE_WIDEN: ClassVar[frozenset] = frozenset({"gain_head", "detail_head"})

    def __post_init__(self) -> None:
        check_ranges(self)
        widths = (*self.enc_channels, 2 * self.enc_channels[0], self.fnet_channels)  # what the blocks normalize
        uneven = sorted({c for c in widths if c % min(self.groups, c)})
        if uneven:
            raise ConfigError(f"groups ({self.groups}) must divide every width (enc_channels and fnet_channels; "
                              f"not {', '.join(map(str, uneven))})")

    @property
    def in_channels(self) -> int:
        return 15 if self.use_error_map else 13

    @property
    def theta_deg(self) -> float:
        if self.cost_volume_theta_deg is not None:
            return self.cost_volume_theta_deg
        nearest = min(COST_VOLUME_THETA_DEG, key=lambda v: abs(v - self.num_views))
        return COST_VOLUME_THETA_DEG[nearest]


def paper_config(**kw) -> NormalNetConfig:
    return NormalNetConfig(**kw)


def cpu_config(**kw) -> NormalNetConfig:
    """Narrower and at half the paper's resolution: trains in about an hour on 2 CPU cores."""
    base = dict(width=128, height=96, enc_channels=(32, 64, 128), fnet_channels=32, groups=8, residual=True)
    base.update(kw)
    return NormalNetConfig(**base)


NORMAL_LOSSES = ("l2", "angle")  # pixel_loss's kinds (lookingglass.normals.train)


@dataclass
class TrainConfig:
    """lr halves every `lr_halve_epochs` (the paper: 1e-4, halved every 2 of 10 epochs)."""

    net: NormalNetConfig = field(default_factory=NormalNetConfig)
    epochs: int = setting(10, "Passes over the scenes.", range=(1, None))
    lr: float = setting(1e-4, "Initial learning rate.", range=(0, None))
    lr_halve_epochs: int = setting(2, "The learning rate halves every this many epochs.", range=(1, None))
    checkpoint_every: int = setting(50, "Steps between checkpoints.", range=(1, None))
    seed: int = setting(0, "Initialization, shuffling and augmentation seed.")
    ior: float = setting(IOR_GLASS, "Index of refraction of the glass.", range=(1.0, 3.0))
    augment: bool = setting(True, "Augment the training scenes.")
    photo_noise: float = setting(0.0, "Chance that an augmented scene is degraded like an 8-bit photo (noise, "
                                      "sRGB quantization).", range=(0, 1))
    mirror_augment: bool = setting(False, "Train on the mirror image of half the steps' scenes (the world mirrored "
                                          "in x = 0, every image flipped, the environment's columns reversed: the "
                                          "physics' own symmetry, which the net otherwise never sees).")
    max_scenes: int = setting(0, "Use only the first N scenes (0: all).", range=(0, None))
    views_per_step: int = setting(0, "Random views of a scene per step (0: all; views are independent images).",
                                  range=(0, None))
    init: str = setting("", "Start from these weights.safetensors (fine-tuning; same network config) instead of "
                            "a random initialization.")
    loss: str = setting("l2", "Per-pixel loss: l2 (the paper's squared L2 of the normals) or angle (~ the angle "
                              "itself, so the pixels the hull already has right weigh as much as the wrong ones).")
    hull_hinge: float = setting(0.0, "Extra weight of the pixels where the net's normal is further from the truth "
                                     "than the hull's it was fed (issue 27: never worse than the input); 0: none.",
                                range=(0, None))
    gain_head_only: bool = setting(False, "Train only the gain head (needs --net.gain-head): every other weight "
                                          "stays as --init gave it; the loss is the quantile (pinball) loss of the "
                                          "predicted gains over the hull's normals.")
    detail_head_only: bool = setting(False, "Train only the detail head (needs --net.detail-head and --init): every "
                                            "other weight stays as --init gave it.")
    gain_quantile: float = setting(0.5, "The quantile of the gain over the hull's normals the gain head learns "
                                        "(lower: a more cautious estimate; 0.5: the median).", range=(0, 1))

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.loss not in NORMAL_LOSSES:
            raise ConfigError(f"loss must be one of {', '.join(NORMAL_LOSSES)}, got {self.loss!r}")
        if self.gain_head_only and not (self.net.gain_head and self.init):
            raise ConfigError("--gain-head-only trains the gain head of trained normals: it needs --net.gain-head "
                              "and --init")
        if self.detail_head_only and not (self.net.detail_head and self.init and not self.gain_head_only):
            raise ConfigError("--detail-head-only trains the detail head of trained normals: it needs "
                              "--net.detail-head and --init, and not --gain-head-only")


# The paper's ablations (Table 1): (use_error_map, use_cost_volume).
VARIANTS = {"basic": (False, False), "wr": (True, False), "wr+cv": (True, True)}
