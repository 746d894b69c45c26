"""Settings of the real-capture commands (`sfm`, `envmap-from-ball`, `import-colmap`, `capture`), as
typed dataclasses: the command line generates its options from them (lookingglass/cliconfig.py) and
each command saves the values it ran with beside its output."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..configio import check_ranges, setting
from ..errors import ConfigError

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


@dataclass
class SfmConfig:
    """Structure from motion with pycolmap (`lookingglass sfm`).

    camera_model: COLMAP camera model shared by every photo (one camera, one set of intrinsics).
    max_image_size: SIFT runs on photos scaled down to this longest side (pixels).
    max_num_features: most SIFT features a photo keeps.
    mask_dilation: object masks (when given) are grown by this fraction of the image diagonal before
        their features are dropped: the object refracts the background, so features on and next to
        it lie about the geometry.
    min_registered: fewer registered photos than this is an error.
    max_axis_miss_deg: a view whose optical axis misses the point all axes meet (least squares) by
        more than this angle is reported by name (a pose that does not fit a shoot around one spot).
    seed: random seed of the mapper (a rerun gives the same model).
    """

    camera_model: str = setting("SIMPLE_RADIAL", "COLMAP camera model shared by all photos: "
                                + ", ".join(CAMERA_MODELS) + ".")
    max_image_size: int = setting(1600, "SIFT on photos scaled to this longest side (pixels).", range=(64, 16384))
    max_num_features: int = setting(8192, "Most SIFT features per photo.", range=(64, None))
    mask_dilation: float = setting(0.02, "Object masks grow by this fraction of the image diagonal before "
                                         "their features are dropped.", range=(0, 0.5))
    min_registered: int = setting(3, "Fewer registered photos than this is an error.", range=(2, None))
    max_axis_miss_deg: float = setting(10.0, "Report a view whose optical axis misses the common point by more "
                                             "(degrees).", range=(0, 90))
    seed: int = setting(0, "Random seed of the mapper.", range=(0, None))

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.camera_model not in CAMERA_MODELS:
            raise ConfigError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, got {self.camera_model!r}")


@dataclass
class BallConfig:
    """Environment map from photos of a mirror ball (`lookingglass envmap-from-ball`).

    reflectance: the ball's mirror reflectance (chrome ~0.6-0.8): the map is the reflection / it.
    max_incidence_deg: reflection samples where the viewing ray meets the ball more obliquely than
        this are not used (near the rim a pixel spans a large solid angle and the fit's error is
        largest).
    edge_samples: radial profiles along which the ball's outline is located to a fraction of a pixel.
    edge_search: the outline is searched within this fraction of the radius either side of the circle.
    min_radius_frac, max_radius_frac: the detector looks for balls with radii in this fraction of
        the photo's shorter side.
    max_candidates: circles kept per photo (Hough's, refined onto an outline; half the best supported,
        half the best by support x radius); the ball is the one circle per photo on the sphere most
        views agree on.
    consistency: how far (centre offset plus radius difference, as a fraction of the circle's
        radius, at least 2 px) a circle may be from a sphere's outline in the photo and still be it.
    max_residual_px: a view whose outline misses the fitted sphere by more (RMS, pixels) is an error.
    """

    reflectance: float = setting(1.0, "The ball's mirror reflectance (the map is the reflection / it).",
                                 range=(0.01, 1.0))
    max_incidence_deg: float = setting(70.0, "Skip reflections seen more obliquely than this (degrees).",
                                       range=(10, 89))
    edge_samples: int = setting(360, "Radial profiles locating the ball's outline.", range=(16, 4096))
    edge_search: float = setting(0.04, "Outline finally searched within this fraction of the radius of the circle.",
                                 range=(0.01, 0.5))
    min_radius_frac: float = setting(0.03, "Smallest ball radius the detector looks for (of the shorter side).",
                                     range=(0.005, 0.5))
    max_radius_frac: float = setting(0.45, "Largest ball radius the detector looks for (of the shorter side).",
                                     range=(0.01, 0.5))
    max_candidates: int = setting(12, "Circles kept per photo as the ball's candidates (one is chosen by all views' "
                                     "agreement).", range=(1, 64))
    consistency: float = setting(0.1, "A circle is on the ball's sphere when its centre and radius are within this "
                                       "fraction of its radius (at least 2 px) of the sphere's.", range=(0.001, 1))
    max_residual_px: float = setting(3.0, "A view's outline off the fitted sphere by more (RMS px) is an error.",
                                     range=(0, None))

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.min_radius_frac >= self.max_radius_frac:
            raise ConfigError(f"min_radius_frac ({self.min_radius_frac}) must be below max_radius_frac "
                              f"({self.max_radius_frac})")


@dataclass
class CaptureConfig:
    """Every setting of the real-capture path: `sfm` and `envmap-from-ball` (and `capture`, which
    chains them with `import-colmap` and `reconstruct`; stop_after: reconstruct's last stage there,
    one of lookingglass.config.STAGES)."""

    sfm: SfmConfig = field(default_factory=SfmConfig)
    ball: BallConfig = field(default_factory=BallConfig)
    stop_after: str = setting("refine", "`capture` only: reconstruct's last stage (visual_hull, normals, surface, "
                                        "refine).")

    def __post_init__(self) -> None:
        from ..config import STAGES

        if self.stop_after not in STAGES:
            raise ConfigError(f"stop_after must be one of {', '.join(STAGES)}, got {self.stop_after!r}")
