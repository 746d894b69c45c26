"""The paper's camera rigs for synthetic scenes (DESIGN.md, "Figures from the paper").

World frame: y up. A camera direction is given by its polar angle theta from +y and its azimuth phi
measured from +z towards +x: origin = distance * (sin theta sin phi, cos theta, sin theta cos phi).
(phi = 0 is the camera on +z looking down -z; phi = 90 deg is on +x.)

10 views (the paper's release): theta in {50, 100} deg +- 10, phi in {0, 72, 144, 216, 288} deg +-
20, uniform jitter; cameras at distance 3 from the world origin, each looking at its own target
jittered by U[-0.05, 0.05]^3, with up = +y + U[-0.1, 0.1]^3 made orthogonal to the view direction.

The 5- and 20-view rigs are not in DESIGN.md; they are chosen so the three rigs differ only in
the number of views, not in the part of the sphere they cover: every rig uses the same two rings
(theta 50 deg, 40 deg above the equator, and 100 deg, 10 deg below it, as the 10-view rig), so each
silhouette set sees the object from above and from slightly below, and the deterministic rigs are
nested, 5 in 10 in 20:
- 5 views: phi in {0, 72, 144, 216, 288} alternating between the rings (50, 100, 50, 100, 50),
  jitter +-10 / +-20 deg -- every other camera of the 10-view rig. (One ring at 75 deg would give
  silhouettes that all look nearly sideways and carve the top and bottom of the hull poorly.)
- 20 views: both rings at phi in {0, 36, ..., 324}, azimuth jitter +-10 deg (the 10-view rig's
  jitter-to-spacing ratio, 20/72, at half the spacing).
Order: by ring (theta 50 first), then by azimuth; for 5 views, by azimuth.
"""

from __future__ import annotations

import numpy as np
import torch

from ..physics.camera import Cameras

from ..physics.constants import PAPER_IMAGE_SIZE, PAPER_RENDER_FOV_X_DEG as PAPER_FOV_X_DEG  # noqa: F401


def rig_layout(num_views: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Nominal angles of a paper rig: polar (V,) and azimuth (V,) in degrees, and the uniform
    jitter half-widths (polar, azimuth) in degrees."""
    if num_views == 10:
        polar = np.repeat([50.0, 100.0], 5)
        azimuth = np.tile(np.arange(5) * 72.0, 2)
        return polar, azimuth, 10.0, 20.0
    if num_views == 5:
        azimuth = np.arange(5) * 72.0
        polar = np.where(np.arange(5) % 2 == 0, 50.0, 100.0)
        return polar, azimuth, 10.0, 20.0
    if num_views == 20:
        polar = np.repeat([50.0, 100.0], 10)
        azimuth = np.tile(np.arange(10) * 36.0, 2)
        return polar, azimuth, 10.0, 10.0
    raise ValueError(f"the paper's rigs have 5, 10 or 20 views, not {num_views}")


def direction_from_angles(polar_deg: np.ndarray, azimuth_deg: np.ndarray) -> np.ndarray:
    """Unit vectors (..., 3): polar from +y, azimuth from +z towards +x."""
    t, p = np.radians(polar_deg), np.radians(azimuth_deg)
    return np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], axis=-1)


def paper_rig_params(num_views: int, rng: np.random.Generator | int | None = None, distance: float = 3.0,
                     deterministic: bool = False, target_jitter: float = 0.05, up_jitter: float = 0.1) -> dict:
    """Look-at parameters of a paper rig, world frame, float64 numpy.

    Returns {"origin": (V, 3), "target": (V, 3), "up": (V, 3) unit and orthogonal to the view
    direction, "polar_deg": (V,), "azimuth_deg": (V,)} (the angles actually used, after jitter).
    rng: numpy Generator or int seed; required unless deterministic (no jitter at all: targets at
    the origin, up = +y made orthogonal).
    """
    polar, azimuth, j_polar, j_azimuth = rig_layout(num_views)
    target = np.zeros((num_views, 3))
    up = np.tile([0.0, 1.0, 0.0], (num_views, 1))
    if not deterministic:
        if rng is None:
            raise ValueError("a jittered rig needs rng (a numpy Generator or an int seed); or pass deterministic=True")
        rng = np.random.default_rng(rng)
        polar = polar + rng.uniform(-j_polar, j_polar, num_views)
        azimuth = azimuth + rng.uniform(-j_azimuth, j_azimuth, num_views)
        target = rng.uniform(-target_jitter, target_jitter, (num_views, 3))
        up = up + rng.uniform(-up_jitter, up_jitter, (num_views, 3))
    origin = distance * direction_from_angles(polar, azimuth)
    forward = target - origin
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    # Gram-Schmidt: the stored up is the camera's true up (Cameras.look_at would derive the same)
    up = up - (up * forward).sum(axis=1, keepdims=True) * forward
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    return {"origin": origin, "target": target, "up": up, "polar_deg": polar, "azimuth_deg": azimuth}


def paper_rig(num_views: int, rng: np.random.Generator | int | None = None, distance: float = 3.0,
              fov_x_deg: float = PAPER_FOV_X_DEG, width: int = PAPER_IMAGE_SIZE[0], height: int = PAPER_IMAGE_SIZE[1],
              deterministic: bool = False, dtype: torch.dtype = torch.float32) -> Cameras:
    """The paper's rig of `num_views` (5, 10 or 20) cameras around a unit-sphere object.

    Returns Cameras with V = num_views views, width x height pixels, fov_x_deg (default 63.4, the
    paper's renders at 480x360). At distance 3 the unit sphere subtends 19.5 deg, inside the
    24.9 deg vertical half field of view, so the object is always fully in frame.
    For the look-at parameters themselves (scene.json), use `paper_rig_params`.
    """
    p = paper_rig_params(num_views, rng, distance, deterministic)
    return Cameras.look_at(p["origin"], p["target"], p["up"], fov_x_deg, width, height, dtype=dtype)
