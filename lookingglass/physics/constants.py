"""Physical and rig constants, defined once (DESIGN.md: the paper's values).

Two fields of view, because the paper has two cameras: its synthetic renderer uses 63.4° for the
480x360 training images, and its real captures' calibrated camera (the `cam*.txt` rig) has
63.349°. Generated data, the shipped weights and the tests use the first; `import-paper` the second.
"""

import math
import numbers

from ..errors import LookingGlassError

IOR_AIR = 1.0003
IOR_GLASS = 1.4723
# The indices of refraction accepted anywhere (scene.json, --ior, configs): from air to beyond
# diamond's 2.42; a value outside is a typo or a unit mix-up, not a glass.
IOR_MIN, IOR_MAX = 1.0, 3.0

PAPER_RENDER_FOV_X_DEG = 63.4  # the paper's synthetic images (and ours)
PAPER_CAPTURE_FOV_X_DEG = 63.349  # the paper's real capture camera
PAPER_IMAGE_SIZE = (480, 360)  # width, height of the paper's rendered images


def check_ior(value, name: str = "ior", fail=LookingGlassError) -> float:
    """`value` as a float when it is a finite number in [IOR_MIN, IOR_MAX]; else raises
    `fail(message)` (an exception class or a function making one) with a message naming `name` and
    the value: the one check of an index of refraction, wherever one comes in."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if not (ok and IOR_MIN <= value <= IOR_MAX):
        raise fail(f"{name} must be an index of refraction from {IOR_MIN} to {IOR_MAX} (glass is about 1.5), "
                   f"got {value}")
    return float(value)


def check_ior_range(bounds, name: str = "ior_range", fail=LookingGlassError, equal_ok: bool = False
                    ) -> tuple[float, float]:
    """(LO, HI) as floats when both pass `check_ior` and LO < HI (LO <= HI with `equal_ok`: a range
    of one value); else raises `fail(message)` naming `name`."""
    lo, hi = (check_ior(v, name, fail) for v in bounds)
    if lo > hi or (lo == hi and not equal_ok):
        raise fail(f"{name}: LO must be {'at most' if equal_ok else 'below'} HI, got {lo} {hi}")
    return lo, hi
