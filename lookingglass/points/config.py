"""The point network's and its trainer's configs (`PointNetConfig`, `PointTrainConfig`) and the
feature columns the net reads, without torch: the command line builds `train-points`' options
(and its --help) from them before torch loads. The network is lookingglass.points.model, the
features lookingglass.points.features, the training lookingglass.points.train.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..config import STRATEGIES
from ..configio import check_ranges, setting
from ..errors import ConfigError
from ..physics.constants import IOR_GLASS

# Column layout of map_features(...)["features"] (N, NUM_FEATURES), world frame:
# point xyz | hull normal | mapped N1 | rendering error | TIR | view cosine (the paper's 12) |
# silhouette-cone counts (ours, one per SILHOUETTE_OFFSETS).
SILHOUETTE_OFFSETS = (0.01, 0.02, 0.04)  # hull-normalized units (the hull's radius is 1)
PAPER_FEATURES = 12  # the paper's columns, before "silhouette"
NUM_FEATURES = PAPER_FEATURES + len(SILHOUETTE_OFFSETS)
FEATURE_COLUMNS: dict[str, slice] = {
    "point": slice(0, 3),
    "hull_normal": slice(3, 6),
    "normal": slice(6, 9),
    "error": slice(9, 10),
    "tir": slice(10, 11),
    "cos": slice(11, 12),
    "silhouette": slice(PAPER_FEATURES, NUM_FEATURES),
}

# The training losses (the keys of lookingglass.points.losses.LOSSES).
POINT_LOSSES = ("nearest", "view", "chamfer")


@dataclass
class PointNetConfig:
    """Sizes and the paper's switches. The defaults are the paper's network (DESIGN.md, "Figures").

    centres / radii / neighbours / sa_mlps: one entry per set-abstraction level, finest first.
    fp_mlps: one entry per feature-propagation level, coarsest first (fp_mlps[0] brings the last
    SA level back to the one before it; fp_mlps[-1] ends at the N input points).
    num_points: the points the stage samples on the hull per shape (the net accepts any N;
    a level with more centres than points keeps all of them).
    """

    # Weights for fewer input columns may start a fine-tune (PointNet.widen_initial_state).
    FINE_TUNE_WIDEN = frozenset({"in_features"})

    in_features: int = setting(NUM_FEATURES, "Input columns read from the features (the first in_features).")
    num_points: int = setting(20000, "Points per cloud the stage samples on the hull.", range=(1, None))
    centres: tuple[int, ...] = (1024, 256, 64, 16)
    radii: tuple[float, ...] = (0.1, 0.2, 0.4, 0.8)
    neighbours: tuple[int, ...] = (64, 32, 32, 32)
    sa_mlps: tuple[tuple[int, ...], ...] = ((64, 64), (128, 128), (256, 256), (512, 512))
    fp_mlps: tuple[tuple[int, ...], ...] = ((512, 256), (256, 128), (128, 64), (64,))
    gn_group_size: int = setting(16, "Channels per GroupNorm group.")
    offset_scale: float = setting(0.25, "offset = offset_scale x tanh(.), in the normalized frame.", range=(0, None))
    average_pooling: bool = setting(True, "Average ball features over the ball's members (else: max pooling).")
    normal_difference: bool = setting(True, "Neighbours' grouping features get their normal minus the centre's.")
    normal_skip: bool = setting(True, "Skip links get the level's normals and their difference to the coarser level's.")
    # Ours, not the paper's: start at the hull (zero offset, the mapped normal); see the module doc.
    residual: bool = setting(False, "Start at the hull: zero offset and the mapped normal (ours).")

    def __post_init__(self) -> None:
        check_ranges(self)
        self.centres = tuple(int(c) for c in self.centres)
        self.radii = tuple(float(r) for r in self.radii)
        self.neighbours = tuple(int(k) for k in self.neighbours)
        self.sa_mlps = tuple(tuple(int(c) for c in m) for m in self.sa_mlps)
        self.fp_mlps = tuple(tuple(int(c) for c in m) for m in self.fp_mlps)
        levels = len(self.centres)
        if levels == 0 or not (len(self.radii) == len(self.neighbours) == len(self.sa_mlps)
                               == len(self.fp_mlps) == levels):
            raise ConfigError("centres, radii, neighbours, sa_mlps and fp_mlps need one entry per level "
                              f"(got {len(self.centres)}, {len(self.radii)}, {len(self.neighbours)}, "
                              f"{len(self.sa_mlps)}, {len(self.fp_mlps)})")
        if any(not m for m in self.sa_mlps + self.fp_mlps):
            raise ConfigError("every MLP needs at least one layer")
        if min(self.centres) < 1 or min(self.neighbours) < 1 or min(self.radii) <= 0:
            raise ConfigError("centres, neighbours and radii must be positive")
        needed = FEATURE_COLUMNS["normal"].stop
        if self.in_features < needed:
            raise ConfigError(f"in_features must hold xyz and the mapped normal (>= {needed}), got {self.in_features}")

    @property
    def levels(self) -> int:
        return len(self.centres)


def paper_config(**kw) -> PointNetConfig:
    return PointNetConfig(**kw)


def cpu_config(**kw) -> PointNetConfig:
    """4096 points, centres 512/128/32/8, neighbours 32/16/16/16, MLP widths halved; residual
    start. 313 158 parameters (paper: 1 232 518). Measured on one core of a busy 2-core machine:
    forward + backward on 4096 points ~0.25 s (forward ~0.18 s, a third of it farthest point
    sampling); the paper preset on 20 000 points ~1.9 s, peak memory ~0.7 GB.
    """
    base = dict(num_points=4096, centres=(512, 128, 32, 8), neighbours=(32, 16, 16, 16),
                sa_mlps=((32, 32), (64, 64), (128, 128), (256, 256)),
                fp_mlps=((256, 128), (128, 64), (64, 32), (32,)), gn_group_size=8, residual=True)
    base.update(kw)
    return PointNetConfig(**base)


@dataclass
class PointTrainConfig:
    """PNet training. loss: one of POINT_LOSSES ("chamfer", the paper's best; "nearest"; "view").
    strategy: feature mapping, AV / NE / RE (the paper's best; "view" needs NE or RE, which
    choose a view per point). lr halves every `lr_halve_epochs`. max_scenes: 0 for all.
    ior: the glass's index of refraction, for the rendering error of the features."""

    net: PointNetConfig = field(default_factory=PointNetConfig)
    loss: str = setting("chamfer", f"Training loss: {', '.join(POINT_LOSSES)} (chamfer: the paper's best).")
    strategy: str = setting("RE", f"Feature mapping: {', '.join(STRATEGIES)} (RE: the paper's best).")
    epochs: int = setting(10, "Passes over the scenes.", range=(1, None))
    lr: float = setting(1e-4, "Initial learning rate.", range=(0, None))
    lr_halve_epochs: int = setting(2, "The learning rate halves every this many epochs.", range=(1, None))
    checkpoint_every: int = setting(50, "Steps between checkpoints.", range=(1, None))
    seed: int = setting(0, "Initialization, shuffling and point-sampling seed.")
    max_scenes: int = setting(0, "Use only the first N scenes (0: all).", range=(0, None))
    ior: float = setting(IOR_GLASS, "Index of refraction of the glass.", range=(1.0, 3.0))
    init: str = setting("", "Start from these weights.safetensors (fine-tuning; same network config) instead of "
                            "a random initialization.")
    unseen_weight: float = setting(0.0, "Chamfer loss: extra weight on ground truth the hull spans (farther than "
                                        "--unseen-distance from its surface), so PNet learns to carve concavities no "
                                        "silhouette shows (0: the paper's loss). 8, as a 10-view fine-tune: the "
                                        "procedural test split's refined CD 0.94 x, the validation shapes' 1.06 x "
                                        "(false carving); the shipped weights use 0 (docs/results.md).",
                                   range=(0, None))
    unseen_distance: float = setting(0.05, "Chamfer loss: where --unseen-weight starts (hull-normalized frame); it "
                                           "reaches its full value at twice this.", range=(0, None))

    def __post_init__(self) -> None:
        self.strategy = str(self.strategy).upper()
        if self.loss not in POINT_LOSSES:
            raise ConfigError(f"unknown point loss {self.loss!r} (choose from {', '.join(POINT_LOSSES)})")
        if self.strategy not in STRATEGIES:
            raise ConfigError(f"unknown feature-mapping strategy {self.strategy!r} "
                              f"(choose from {', '.join(STRATEGIES)})")
        if self.loss == "view" and self.strategy == "AV":
            raise ConfigError('the "view" loss needs a strategy that chooses a view (NE or RE), not AV')
        if self.unseen_weight > 0 and self.loss != "chamfer":
            raise ConfigError(f'--unseen-weight weighs the Chamfer loss\'s ground-truth samples; the {self.loss!r} '
                              'loss has none')
        check_ranges(self)
