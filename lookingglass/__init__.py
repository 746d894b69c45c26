"""lookingglass: 3D reconstruction of transparent shapes from a few photos under a known
environment map (after Li et al., "Through the Looking Glass", CVPR 2020)."""

__version__ = "0.1.0"

from .errors import LookingGlassError  # noqa: E402,F401
