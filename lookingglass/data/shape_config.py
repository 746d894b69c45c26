"""The procedural shapes' settings (`ShapeConfig`), apart from the code that builds them
(lookingglass/data/shapes.py, which imports trimesh, pymeshlab and scikit-image): the dataset's config
holds one, and `lookingglass generate` checks its options before it loads those."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import ConfigError

KINDS = ("ellipsoid", "box", "cylinder", "capsule", "torus", "plate", "rod")
CARVE_KINDS = ("dent", "groove", "hole")


@dataclass(frozen=True)
class ShapeConfig:
    """Parameters of the shape distribution and of the meshing.

    Lengths are in the construction frame, where the first (largest) primitive has half-extents of
    about 0.45-0.9; the final mesh is rescaled to the unit sphere, so only ratios matter.
    """

    target_faces: int = 24000
    """Marching cubes makes about 2 faces per voxel^2 of surface, so the grid resolution is chosen
    from a coarse pre-pass to give about this many faces (cheaper than simplifying afterwards)."""
    resolution: tuple[int, int] = (64, 128)
    """Range of grid samples along the longest side of the shape's bounding box (cubic voxels)."""
    coarse_resolution: int = 40
    """Resolution of the pre-pass that measures the surface area."""
    num_primitives: tuple[int, int] = (1, 5)
    """Inclusive range of the number of additive primitives."""
    kind_weights: dict[str, float] = field(default_factory=lambda: {
        "ellipsoid": 3.0, "box": 2.0, "cylinder": 1.5, "capsule": 1.5, "torus": 1.0, "plate": 1.0, "rod": 1.0})
    """Relative frequency of each primitive kind (names from `KINDS`)."""
    first_size: tuple[float, float] = (0.45, 0.9)
    """Half-extent range of the first primitive (the body)."""
    part_size: tuple[float, float] = (0.2, 0.6)
    """Half-extent range of the later primitives (parts attached to the body)."""
    thin_half_thickness: tuple[float, float] = (0.04, 0.08)
    """Half thickness of plates and radius of rods. Keep >= ~1.2 voxels of the coarsest grid
    (extent ~2.2 / resolution[0]) or thin parts break up."""
    blend: tuple[float, float] = (0.03, 0.2)
    """Range of the smooth-union / smooth-subtraction radius k (polynomial smooth min)."""
    p_carve: float = 0.4
    """Chance that a shape gets carved by smooth subtraction (concavities, through-holes)."""
    max_carves: int = 2
    noise_amplitude: tuple[float, float] = (0.0, 0.02)
    """Range of the standard deviation of the additive low-frequency noise on the field (kept
    below the thin parts' half thickness, or rods and plates pinch off)."""
    noise_frequency: tuple[float, float] = (1.0, 3.5)
    """Range of the noise's angular frequency scale (radians per unit length)."""
    noise_terms: int = 12
    max_faces: int = 40000
    """Meshes with more faces (rare: the pre-pass estimate was off) are simplified to
    target_faces (quadric edge collapse, topology preserved)."""
    min_faces: int = 2000
    """A shape with fewer faces after meshing is rejected and redrawn (degenerate draw)."""
    taubin_steps: int = 10
    """Taubin smoothing steps (lambda 0.5, mu -0.53): removes marching-cubes ripples without
    shrinking. 0 disables."""
    projection_steps: int = 3
    """Newton steps projecting the vertices onto the exact zero set of the analytic field."""
    max_tries: int = 8

    def __post_init__(self) -> None:
        """Bad settings are refused here, not found by every draw failing (or a NumPy traceback)."""
        def fail(name: str, want: str, got) -> ConfigError:
            return ConfigError(f"shape.{name} must be {want}, got {got}")

        for name in ("resolution", "num_primitives", "first_size", "part_size", "thin_half_thickness", "blend",
                     "noise_amplitude", "noise_frequency"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
                raise fail(name, "LO HI with 0 <= LO <= HI (finite)", f"{lo} {hi}")
        if self.resolution[0] < 8 or self.coarse_resolution < 8:
            raise fail("resolution", "at least 8 (and coarse_resolution too)",
                       f"{self.resolution}, {self.coarse_resolution}")
        if self.num_primitives[0] < 1:
            raise fail("num_primitives", "at least 1", self.num_primitives[0])
        for name in ("target_faces", "max_faces", "max_tries"):
            if getattr(self, name) < 1:
                raise fail(name, "at least 1", getattr(self, name))
        for name in ("min_faces", "max_carves", "noise_terms", "taubin_steps", "projection_steps"):
            if getattr(self, name) < 0:
                raise fail(name, "at least 0", getattr(self, name))
        if not 0 <= self.p_carve <= 1:
            raise fail("p_carve", "in [0, 1]", self.p_carve)
        weights = dict(self.kind_weights)
        if set(weights) - set(KINDS) or not all(math.isfinite(w) and w >= 0 for w in weights.values()) \
                or sum(weights.values()) <= 0:
            raise fail("kind_weights", f"non-negative weights of {', '.join(KINDS)}, not all 0", weights)
