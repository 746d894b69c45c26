"""The environment map from photos of a mirror ball (`lookingglass envmap-from-ball`).

1. **Find the ball** in each photo: the user's circle (`--circles FILE`, one `stem cx cy r` line
   each, pixels of the photo as shot, centre of the top-left pixel at (0.5, 0.5)) or, by the
   calibration: each photo's candidate circles (OpenCV's Hough transform, `cv2.HOUGH_GRADIENT_ALT`,
   each refined onto an outline and scored), then the one sphere that most views agree on (every
   pair of candidates in two views triangulates a sphere from their cones of rays; the sphere with a
   candidate within `consistency` in the most views wins), and per photo its candidate on that
   sphere; a photo with none is refused by name. Discs in the room and circles mirrored inside the
   ball fit no sphere the other views see. The outline is then located to a fraction of a pixel
   along `edge_samples` radial profiles (the outermost clear brightness step within `edge_search` x
   r of the circle: inside the rim the ball shows the room squeezed, with steeper steps than the
   rim's own).
2. **Triangulate the sphere** from the calibrated views (COLMAP model): every outline point gives
   a ray tangent to the ball (undistorted with the model's own camera equations), and the centre C
   and radius rho minimise the angular misfit asin(|(C - O) x d| / |C - O|) - asin(rho / |C - O|)
   over all of them (least squares, soft-L1 loss against outliers such as the ball's stand). No tape
   measure: the model's scale fixes rho. Each view's RMS misfit, in pixels, is reported.
3. **Unwrap** each view: for every texel direction w of the output map (model's world frame,
   `physics.environment.texel_directions`, the envmap convention's own texel placement), the point
   of the ball that mirrors w into the camera (normal n = normalize(w - d_in), refined by fixed-point
   iterations on the viewing ray d_in to that point), projected into the photo (with distortion)
   and sampled bilinearly. Points seen more obliquely than `max_incidence_deg` are not used.
4. **Merge** by the per-texel median over the views (the photographer and the camera, seen near
   the ball's centre in each view, are outvoted), divide by the reflectance, and fill the texels no
   view saw (right behind the ball) by normalized convolution from their neighbours.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from ..errors import LookingGlassError
from ..fileio import check_output_dir, within, write_json
from ..physics.environment import texel_directions
from .colmap import ColmapView, read_model
from .config import BallConfig
from .images import HDR_SUFFIXES, check_image_size, linear_to_srgb, read_image, write_image
from .paper_import import PHOTO_SUFFIXES, _list_files, natural_key

Circle = tuple[float, float, float]  # cx, cy, r in continuous pixel coordinates


def read_circles(path: str | os.PathLike) -> dict[str, Circle]:
    """A circles file: one `stem cx cy r` line per photo ('#' comments and blank lines skipped)."""
    path = Path(path)
    if not path.is_file():
        raise LookingGlassError("circles file not found" if not path.exists() else "not a file", path)
    circles: dict[str, Circle] = {}
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        tokens = line.split("#", 1)[0].split()
        if not tokens:
            continue
        try:
            cx, cy, r = (float(t) for t in tokens[1:])
            ok = len(tokens) == 4 and all(map(math.isfinite, (cx, cy, r))) and r > 0
        except ValueError:
            ok = False
        if not ok:
            raise LookingGlassError(f"line {n}: expected 'stem cx cy r' (r > 0), got '{line.strip()}'", path)
        circles[tokens[0]] = (cx, cy, r)
    return circles


def _grey8(image: np.ndarray) -> np.ndarray:
    """8-bit sRGB-encoded luminance (H, W) of a linear image (H, W, 3)."""
    lum = image @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    return np.round(linear_to_srgb(lum / max(float(np.percentile(lum, 99.5)), 1e-6)) * 255).astype(np.uint8)


def _hough_candidates(image: np.ndarray, config: BallConfig, count: int = 12) -> list[Circle]:
    """Circles of the photo (H, W, 3) linear with radii in the configured range, strongest first
    (Hough on a copy scaled to at most 1024 px). Continuous pixel coordinates."""
    grey = _grey8(image)
    scale = min(1.0, 1024 / max(grey.shape))
    small = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else grey
    small = cv2.GaussianBlur(small, (0, 0), 1.0)
    side = min(small.shape)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # threaded, its order of equal-vote circles (and so which are returned) varies
    try:
        found = cv2.HoughCircles(small, cv2.HOUGH_GRADIENT_ALT, dp=1.5, minDist=2,
                                 param1=100, param2=0.5, minRadius=max(4, int(config.min_radius_frac * side)),
                                 maxRadius=int(config.max_radius_frac * side))
    finally:
        cv2.setNumThreads(threads)
    if found is None:
        return []
    return [(float(x) / scale + 0.5, float(y) / scale + 0.5, float(r) / scale) for x, y, r in found[0][:count]]


def fit_circle(points: np.ndarray) -> Circle:
    """Least-squares (Kasa) circle through points (N, 2)."""
    x, y = points[:, 0], points[:, 1]
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    (a, b, c), *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    cx, cy = a / 2, b / 2
    return float(cx), float(cy), float(math.sqrt(max(c + cx * cx + cy * cy, 1e-12)))


def refine_circle(image: np.ndarray, circle: Circle, config: BallConfig = BallConfig()) -> tuple[Circle, float]:
    """A circle moved onto the ball's outline: outline points searched around it (widely first),
    a circle fitted to those within 1.5 px of the previous fit, three rounds. Returns the circle and
    its support: the fraction of radial profiles whose outline point lies within 1.5 px of it."""
    support = 0.0
    for search in (0.3, 0.12, config.edge_search):
        pts = outline_points(image, circle, config, search=search, keep_weak=True)
        for _ in range(3):
            dist = np.abs(np.hypot(pts[:, 0] - circle[0], pts[:, 1] - circle[1]) - circle[2])
            near = pts[dist < max(1.5, 0.5 * np.median(dist) + 1.0)]
            if len(near) < 8:
                return circle, 0.0
            circle = fit_circle(near)
        dist = np.abs(np.hypot(pts[:, 0] - circle[0], pts[:, 1] - circle[1]) - circle[2])
        support = float((dist < 1.5).mean())
    return circle, support


def ball_candidates(image: np.ndarray, config: BallConfig = BallConfig()) -> list[tuple[Circle, float]]:
    """Circles that may be the mirror ball in a photo (H, W, 3) linear, with their support (the
    fraction of the outline found on them): Hough's (up to 4 x config.max_candidates), each refined
    onto an outline (`refine_circle`), those with at least 30% support, duplicates (centre and
    radius within 10% of the radius) dropped; kept: the best half of config.max_candidates by support
    and the best by support x radius (a ball mirrors round things into smaller, sharper circles
    inside its own outline; a busy room has large faint ones)."""
    refined = [refine_circle(image, c, config) for c in _hough_candidates(image, config, 4 * config.max_candidates)]
    unique: list[tuple[Circle, float]] = []
    for circle, support in sorted(refined, key=lambda cs: -cs[1]):  # a few dozen circles
        if support >= 0.3 and all(max(abs(circle[0] - o[0]), abs(circle[1] - o[1]), abs(circle[2] - o[2]))
                                  >= 0.1 * o[2] for o, _ in unique):
            unique.append((circle, support))
    half = (config.max_candidates + 1) // 2
    by_size = sorted(unique, key=lambda cs: -cs[1] * cs[0][2])
    return unique[:half] + [cs for cs in by_size if cs not in unique[:half]][:config.max_candidates - half]


def detect_ball(image: np.ndarray, config: BallConfig = BallConfig()) -> Circle | None:
    """The ball in a photo alone (no other view to agree with), or None: of its `ball_candidates`, the
    one with the largest support x radius (a ball mirrors round things into smaller circles inside
    its own outline, whose edges can be sharper than the ball's rim)."""
    found = ball_candidates(image, config)
    return max(found, key=lambda cs: cs[1] * cs[0][2])[0] if found else None


def circle_cone(view: ColmapView, circle: Circle, samples: int = 32) -> tuple[np.ndarray, float]:
    """The cone of rays (model frame) through a circle of the photo (lens distortion undone): its unit
    axis (3,) (mean of the rays) and half-angle (radians, their mean angle to it). A sphere seen by
    the camera is such a cone, its axis through the centre, sin(half-angle) = radius / distance."""
    theta = np.linspace(0, 2 * np.pi, samples, endpoint=False)
    pts = np.stack([circle[0] + circle[2] * np.cos(theta), circle[1] + circle[2] * np.sin(theta)], -1)
    rays = tangent_rays(view, pts)
    axis = rays.mean(axis=0)
    axis /= np.linalg.norm(axis)
    return axis, float(np.arccos(np.clip(rays @ axis, -1, 1)).mean())


def consistent_sphere(origins: np.ndarray, axes: np.ndarray, half: np.ndarray, view_of: np.ndarray,
                      tolerance: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The one sphere most views agree on, from candidate cones (`circle_cone`) of V views.

    origins (V, 3): camera centres; axes (N, 3), half (N,) radians: every candidate's cone; view_of (N,)
    int: its view; tolerance (N,) radians: how far (axis angle + half-angle difference) a candidate
    may lie from a sphere's cone and still see it. Every pair of candidates in two views gives a
    sphere (its centre where the two axes pass closest, radius from the half-angles; pairs whose axes
    miss each other or whose radii disagree by more than the tolerance are dropped); the sphere with
    the most views holding a candidate within tolerance wins (ties: the least summed misfit).
    Returns the chosen candidate per view (V,) int (-1: none fits), the centre (3,) and radius."""
    V = len(origins)
    O = origins[view_of]
    i, j = np.triu_indices(len(axes), 1)
    keep = view_of[i] != view_of[j]
    i, j = i[keep], j[keep]
    # closest points of the axis lines O_i + s a_i and O_j + t a_j
    a, b, w = axes[i], axes[j], O[i] - O[j]
    ab, aw, bw = (a * b).sum(-1), (a * w).sum(-1), (b * w).sum(-1)
    den = np.maximum(1 - ab ** 2, 1e-12)
    s, t = (ab * bw - aw) / den, (bw - ab * aw) / den
    pi, pj = O[i] + s[:, None] * a, O[j] + t[:, None] * b
    centre = (pi + pj) / 2
    rho_i = np.linalg.norm(centre - O[i], axis=1) * np.sin(half[i])
    rho_j = np.linalg.norm(centre - O[j], axis=1) * np.sin(half[j])
    rho = (rho_i + rho_j) / 2
    near = np.minimum(np.linalg.norm(centre - O[i], axis=1), np.linalg.norm(centre - O[j], axis=1))
    tol = np.minimum(tolerance[i], tolerance[j])
    ok = ((s > 0) & (t > 0) & (ab < 1 - 1e-9) & (np.linalg.norm(pi - pj, axis=1) < near * tol)
          & (np.abs(rho_i - rho_j) < near * tol))
    if not ok.any():
        return np.full(V, -1), np.full(3, np.nan), float("nan")
    centre, rho = centre[ok], rho[ok]
    rel = centre[:, None] - O[None]  # (M, N, 3)
    dist = np.linalg.norm(rel, axis=-1)
    axis_err = np.arccos(np.clip((rel * axes[None]).sum(-1) / dist, -1, 1))
    misfit = axis_err + np.abs(np.arcsin(np.clip(rho[:, None] / dist, 0, 1)) - half[None])
    misfit = np.where(dist > rho[:, None], misfit, np.inf) / tolerance[None]  # in tolerances
    members = [np.flatnonzero(view_of == v) for v in range(V)]  # V views, not pixels
    best = np.stack([misfit[:, m].min(1) if len(m) else np.full(len(centre), np.inf) for m in members], 1)
    seen = best <= 1  # (M, V)
    score = seen.sum(1) - np.where(seen, best, 0).sum(1) / (V + 1)  # more views first, then less misfit
    h = int(np.argmax(score))
    chosen = np.array([m[int(np.argmin(misfit[h, m]))] if seen[h, v] else -1 for v, m in enumerate(members)])
    return chosen, centre[h], float(rho[h])


def outline_points(image: np.ndarray, circle: Circle, config: BallConfig = BallConfig(),
                   search: float | None = None, keep_weak: bool = False) -> np.ndarray:
    """The ball's outline near `circle`: (N, 2) continuous pixel coordinates, one per radial profile
    (within `search`, default config.edge_search, x r of the circle) whose brightness step is clear
    (>= 1/3 of the median step, unless keep_weak), located to sub-pixel by a parabola through the
    steepest step."""
    search = config.edge_search if search is None else search
    grey = image @ np.array([0.2126, 0.7152, 0.0722], np.float32)  # linear: a box-filtered edge is steepest on it
    cx, cy, r = circle
    theta = np.linspace(0, 2 * np.pi, config.edge_samples, endpoint=False)
    step = 0.25
    radii = np.arange(r * (1 - search), r * (1 + search) + step, step)
    xs = (cx + np.cos(theta)[:, None] * radii[None]).astype(np.float32)
    ys = (cy + np.sin(theta)[:, None] * radii[None]).astype(np.float32)
    profile = cv2.remap(grey, xs - 0.5, ys - 0.5, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    grad = np.abs(np.gradient(profile, axis=1))
    # the outermost clear step (a local peak >= 1/3 of the profile's steepest): inside its outline a
    # mirror ball shows the room squeezed towards the rim, whose steps are often steeper than the rim's
    rows = np.arange(len(theta))
    peak = np.zeros_like(grad, dtype=bool)
    peak[:, 1:-1] = (grad[:, 1:-1] >= grad[:, :-2]) & (grad[:, 1:-1] >= grad[:, 2:])
    strong = peak & (grad >= grad.max(axis=1, keepdims=True) / 3)
    k = np.where(strong.any(axis=1), grad.shape[1] - 1 - strong[:, ::-1].argmax(axis=1), grad.argmax(axis=1))
    strength = grad[rows, k]
    # the centroid of the gradient's upper half within 1.5 px of that peak: a box-filtered edge,
    # resampled bilinearly, has a flat-topped gradient whose argmax alone sits on its inner side
    window = np.abs(np.arange(len(radii))[None] - k[:, None]) <= int(round(1.5 / step))
    weight = np.where(window, np.clip(grad - 0.5 * strength[:, None], 0, None), 0.0)
    rad = (weight * radii[None]).sum(axis=1) / np.maximum(weight.sum(axis=1), 1e-12)
    keep = np.ones(len(theta), bool) if keep_weak else strength >= max(1e-6, np.median(strength) / 3)
    return np.stack([cx + np.cos(theta) * rad, cy + np.sin(theta) * rad], axis=-1)[keep]


def tangent_rays(view: ColmapView, points: np.ndarray) -> np.ndarray:
    """Unit world directions (N, 3) (model frame) of the rays through pixel points (N, 2)."""
    norm = np.asarray(view.camera.cam_from_img(np.asarray(points, np.float64)), np.float64)
    cam = np.concatenate([norm, np.ones((len(norm), 1))], axis=1)
    cam /= np.linalg.norm(cam, axis=1, keepdims=True)
    return cam @ view.rotation  # R^T applied to each row


def fit_sphere(origins: np.ndarray, rays: list[np.ndarray]) -> tuple[np.ndarray, float, np.ndarray]:
    """Sphere (centre (3,), radius) tangent to every ray: origins (V, 3), rays[v] (N_v, 3) unit.
    Returns also each view's RMS angular misfit (V,) in radians."""
    from scipy.optimize import least_squares

    axes = np.stack([r.mean(axis=0) / np.linalg.norm(r.mean(axis=0)) for r in rays])
    half = np.array([np.arccos(np.clip(r @ a, -1, 1)).mean() for r, a in zip(rays, axes)])
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    c0 = np.linalg.lstsq(proj.sum(0), np.einsum("vij,vj->i", proj, origins), rcond=None)[0]
    rho0 = float(np.mean(np.linalg.norm(c0 - origins, axis=1) * np.sin(half)))
    O = np.concatenate([np.repeat(o[None], len(r), 0) for o, r in zip(origins, rays)])
    D = np.concatenate(rays)
    view_of = np.concatenate([np.full(len(r), i) for i, r in enumerate(rays)])

    def misfit(x: np.ndarray) -> np.ndarray:
        rel = x[:3] - O
        dist = np.linalg.norm(rel, axis=1)
        return (np.arcsin(np.clip(np.linalg.norm(np.cross(rel, D), axis=1) / dist, 0, 1))
                - np.arcsin(np.clip(x[3] / dist, 0, 1)))

    scale = float(np.median(half)) / 50
    fit = least_squares(misfit, np.concatenate([c0, [rho0]]), loss="soft_l1", f_scale=max(scale, 1e-6),
                        x_scale=np.full(4, max(rho0, 1e-9)))
    res = misfit(fit.x)
    rms = np.sqrt(np.bincount(view_of, res ** 2, minlength=len(rays)) / np.bincount(view_of, minlength=len(rays)))
    return fit.x[:3], float(fit.x[3]), rms


def unwrap_view(image: np.ndarray, view: ColmapView, centre: np.ndarray, radius: float, directions: np.ndarray,
                max_incidence_deg: float, iterations: int = 5) -> np.ndarray:
    """One view's reflection as a map: for directions (..., 3) (model frame), the radiance (..., 3)
    the ball mirrors from them into this photo (H, W, 3) linear, NaN where the view does not see it
    (behind the ball, too oblique, outside the photo)."""
    o = view.origin
    w = directions.reshape(-1, 3)
    d_in = np.broadcast_to((centre - o) / np.linalg.norm(centre - o), w.shape)
    for _ in range(iterations):
        n = w - d_in
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        p = centre + radius * n
        d_in = (p - o) / np.linalg.norm(p - o, axis=1, keepdims=True)
    cos_inc = -(d_in * n).sum(axis=1)
    cam = p @ view.rotation.T + view.translation
    ok = (cos_inc > math.cos(math.radians(max_incidence_deg))) & (cam[:, 2] > 0)
    xy = np.full((len(w), 2), -1e6)
    if ok.any():
        xy[ok] = np.asarray(view.camera.img_from_cam(cam[ok]), np.float64)
    H, W = image.shape[:2]
    ok &= (xy[:, 0] >= 0.5) & (xy[:, 0] <= W - 0.5) & (xy[:, 1] >= 0.5) & (xy[:, 1] <= H - 0.5)
    cols = directions.shape[-2] if directions.ndim >= 3 else 1  # cv2.remap maps stay under 32767 rows
    m = (xy - 0.5).astype(np.float32).reshape(-1, cols, 2)
    values = cv2.remap(image, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)
    values = np.where(ok[:, None], values, np.nan)
    return values.reshape(*directions.shape[:-1], 3).astype(np.float32)


def fill_holes(env: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Texels where `valid` (H, W) is False get the blurred average of the valid ones around them
    (normalized convolution, widening until every texel is filled)."""
    out = np.where(valid[..., None], env, 0).astype(np.float32)
    have = valid.astype(np.float32)
    filled = valid.copy()
    sigma = 1.0
    while not filled.all() and sigma < 4 * max(env.shape[:2]):
        num = cv2.GaussianBlur(np.where(valid[..., None], env, 0).astype(np.float32), (0, 0), sigma)
        den = cv2.GaussianBlur(have, (0, 0), sigma)
        new = ~filled & (den > 1e-3)
        out[new] = num[new] / den[new, None]
        filled |= new
        sigma *= 2
    return out


def outline_inliers(image: np.ndarray, ball: "BallView", config: BallConfig) -> np.ndarray:
    """The outline points (N, 2) of the ball within 1.5 px of its circle, after refining the circle
    onto the outline (`refine_circle`; it replaces ball.circle). Raises LookingGlassError naming the
    photo when the outline is not clear."""
    circle, support = refine_circle(image, ball.circle, config)
    pts = outline_points(image, circle, config, keep_weak=True)
    pts = pts[np.abs(np.hypot(pts[:, 0] - circle[0], pts[:, 1] - circle[1]) - circle[2]) < 1.5]
    if support < 0.3 or len(pts) < 8:
        raise LookingGlassError(f"the ball's outline is not clear in this photo (only {100 * support:.0f}% of it "
                                f"found around the circle {', '.join(f'{v:.1f}' for v in ball.circle)}); give "
                                "its circle in --circles FILE", ball.photo)
    ball.circle = circle
    return pts


@dataclass
class BallView:
    """One ball photo: its file, the model's view of it, the circle used and where it came from."""

    photo: Path
    view: ColmapView
    circle: Circle
    source: str  # "detected" or "circles file"


def _circle_fits(circle: Circle, width: int, height: int) -> bool:
    """A ball no larger than the photo that shows at least part of it (its centre nearer the photo
    than its radius)."""
    cx, cy, r = circle
    outside = math.hypot(max(0.0, -cx, cx - width), max(0.0, -cy, cy - height))
    return r <= max(width, height) and outside < r


def _ball_views(model, images: Path, circles: dict[str, Circle] | None, config: BallConfig,
                photos: dict[Path, np.ndarray]) -> list[BallView]:
    """Each ball photo with its circle: the user's (circles file) or, of its `ball_candidates`, the
    one on the sphere that most views agree on (`consistent_sphere`). Raises LookingGlassError
    naming a photo where no circle fits that sphere."""
    files = _list_files(images, PHOTO_SUFFIXES + tuple(HDR_SUFFIXES), "ball photo")
    paths = sorted((p for ps in files.values() for p in ps), key=lambda p: natural_key(p.name))
    if not paths:
        raise LookingGlassError(f"no photos ({'/'.join(PHOTO_SUFFIXES)}) in this folder", images)
    if len(paths) < 2:
        raise LookingGlassError(f"{len(paths)} ball photo here: the ball's position needs at least 2 views", images)
    views, candidates = [], []
    for path in paths:
        view = model.view_for(path)
        img = read_image(path, "srgb")
        if (img.shape[1], img.shape[0]) != (view.camera.width, view.camera.height):
            raise LookingGlassError(f"photo is {img.shape[1]}x{img.shape[0]} but its camera in the COLMAP model "
                                    f"({view.name}) is {view.camera.width}x{view.camera.height}", path)
        photos[path] = img
        views.append(view)
        user = circles is not None and path.stem in circles
        if user and not _circle_fits(circles[path.stem], img.shape[1], img.shape[0]):
            raise LookingGlassError(f"its circle in the circles file ({' '.join(f'{v:g}' for v in circles[path.stem])}) "
                                    f"does not fit this {img.shape[1]}x{img.shape[0]} photo (its radius must be at "
                                    "most the photo's size and the circle must overlap it)", path)
        candidates.append([(circles[path.stem], "circles file")] if user
                          else [(c, "detected") for c, _ in ball_candidates(img, config)])
    flat = [(v, c, source) for v, cands in enumerate(candidates) for c, source in cands]
    if not flat:
        raise LookingGlassError("mirror ball not found in any photo here (give its circles in --circles FILE: "
                                "'stem cx cy r' lines)", images)
    cones = [circle_cone(views[v], c) for v, c, _ in flat]
    focal = np.array([float(views[v].camera.mean_focal_length()) for v, _, _ in flat])
    tolerance = np.array([max(config.consistency * c[2], 2.0) for _, c, _ in flat]) / focal
    chosen, _, _ = consistent_sphere(np.stack([v.origin for v in views]), np.stack([a for a, _ in cones]),
                                     np.array([h for _, h in cones]), np.array([v for v, _, _ in flat]), tolerance)
    agree = int((chosen >= 0).sum())
    for path, cands, k in zip(paths, candidates, chosen):
        if k < 0 and cands and cands[0][1] == "circles file":
            raise LookingGlassError(f"this photo's circle in the circles file is not on the sphere the other {agree} "
                                    "photos agree on (a wrong circle, or a pose that does not fit)", path)
        if k < 0:
            what = ("no circle in it" if not cands else "no two photos agree on a sphere" if agree < 2 else
                    f"none of its {len(cands)} circles is on the sphere the other {agree} photos agree on")
            raise LookingGlassError(f"mirror ball not found in this photo ({what}); give its circle in --circles "
                                    f"FILE: '{path.stem} cx cy r'", path)
    return [BallView(path, view, *flat[k][1:]) for path, view, k in zip(paths, views, chosen)]


def envmap_from_ball(model: str | os.PathLike, images: str | os.PathLike, out: str | os.PathLike,
                     circles: str | os.PathLike | None = None, size: tuple[int, int] = (1024, 512),
                     config: BallConfig = BallConfig(), force: bool = False) -> dict:
    """Build the environment map (model's world frame) from the mirror-ball photos in `images`
    (every photo there must be in the COLMAP `model`); write it to `out` (.hdr or .exr), a preview
    `<out stem>.preview.png` and the fit `<out stem>.ball.json` beside it (centre, radius, each
    view's circle and RMS misfit in pixels). Returns that record. Refuses to replace existing files
    unless force. Raises LookingGlassError naming the photo at fault (no ball found, a photo not in
    the model, another size, a view that does not fit the sphere)."""
    model, images, out = Path(model), Path(images), Path(out)
    W, H = check_image_size(size, "--size")
    if W != 2 * H:
        raise LookingGlassError(f"--size must be W H with W = 2 H (equirectangular), got {W} {H}")
    if out.suffix.lower() not in (".hdr", ".exr"):
        raise LookingGlassError("the environment map must be written as .hdr or .exr", out)
    preview, record_path = out.with_suffix(".preview.png"), out.with_suffix(".ball.json")
    if not force:
        for p in (out, preview, record_path):
            if p.exists():
                raise LookingGlassError("already exists (use --force to replace it)", p)
    for p in (out, preview, record_path):  # never over an input photo, nor into the folders read
        for folder in (images, model):
            if within(p, folder):
                raise LookingGlassError(f"is inside the input folder {folder}; write the map elsewhere", p)
    check_output_dir(out.parent, True)  # a folder we may write (made if missing)
    colmap = read_model(model)
    user_circles = read_circles(circles) if circles is not None else None
    if user_circles is not None and Path(images).is_dir():
        stems = {p.stem for p in Path(images).iterdir() if p.is_file()}
        unknown = sorted(set(user_circles) - stems)
        if unknown:  # a typo would otherwise be ignored, and the ball then "not found" in that photo
            raise LookingGlassError(f"circles given for {', '.join(unknown)}: no photo of that name in {images}",
                                    circles)
    photos: dict[Path, np.ndarray] = {}
    views = _ball_views(colmap, images, user_circles, config, photos)

    rays = [tangent_rays(v.view, outline_inliers(photos[v.photo], v, config)) for v in views]
    origins = np.stack([v.view.origin for v in views])
    centre, radius, rms = fit_sphere(origins, rays)
    focal = np.array([float(v.view.camera.mean_focal_length()) for v in views])
    rms_px = rms * focal
    worst = int(np.argmax(rms_px))
    if rms_px[worst] > config.max_residual_px:
        raise LookingGlassError(f"the ball's outline in this photo misses the sphere fitted to all views by "
                                f"{rms_px[worst]:.1f} px RMS (limit {config.max_residual_px}): a wrong circle, or "
                                "a pose that does not fit", views[worst].photo)

    dirs = texel_directions(H, dtype=torch.float64).numpy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN texels: nobody saw them
        stack = np.stack([unwrap_view(photos[v.photo], v.view, centre, radius, dirs, config.max_incidence_deg)
                          for v in views])
        merged = np.nanmedian(stack, axis=0)
    seen = np.isfinite(merged).all(axis=-1)
    env = fill_holes(np.nan_to_num(merged) / config.reflectance, seen)
    record = {"model": str(colmap.path), "frame": "the COLMAP model's world frame",
              "centre": centre.tolist(), "radius": radius, "coverage": float(seen.mean()),
              "views": [{"photo": str(v.photo), "model_image": v.view.name, "circle": list(v.circle),
                         "circle_from": v.source, "outline_points": int(len(r)), "residual_px": float(e)}
                        for v, r, e in zip(views, rays, rms_px)],
              "config": asdict(config)}
    peak = max(float(np.percentile(env, 99)), 1e-6)
    write_json(record_path, record)
    write_image(preview, np.clip(env / peak, 0, 1))
    write_image(out, env)
    return record


__all__ = ["read_circles", "ball_candidates", "detect_ball", "circle_cone", "consistent_sphere", "outline_points", "tangent_rays", "fit_sphere", "unwrap_view",
           "fill_holes", "envmap_from_ball"]
