"""The environment map pool for synthetic scenes: natural HDR maps, augmented, and procedural maps.

All maps follow the project convention (DESIGN.md, = Mitsuba 3 `envmap`): equirectangular, float32
(H, 2H, 3) linear radiance; direction d = (x, y, z) maps to u = atan2(x, -z) / (2 pi) mod 1,
v = acos(y) / pi; columns are texel-centred (u = (j + 1/2) / W), rows run from the +y pole
(row 0) to the -y pole (row H - 1), as `lookingglass.physics.environment.EnvironmentMap` samples.

The paper trains on 1499 Laval indoor HDR maps; this pool has a handful of natural maps
(`../shared/envmaps`), so it multiplies them by augmentation (rotation about the up axis,
mirroring, exposure, white balance) and mixes in procedural maps -- sky gradients, bright sources
and high-frequency textures (glass is only informative where the background has texture), drawn
from a seed, so the pool is effectively unbounded.

Every map an `EnvmapSampler` yields comes with a small JSON-able description from which
`envmap_from_description` regenerates it exactly, so a dataset scene can record its lighting.
"""

from __future__ import annotations

import functools
import itertools
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from ..capture.images import read_envmap
from ..errors import LookingGlassError

ENVMAP_SUFFIXES = (".hdr", ".exr")
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 weights of linear RGB


def default_envmap_folder() -> Path:
    """$LOOKINGGLASS_ENVMAPS if set, else `shared/envmaps` beside the repository checkout."""
    env = os.environ.get("LOOKINGGLASS_ENVMAPS")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "envmaps"


def natural_envmaps(folder: str | os.PathLike | None = None) -> list[Path]:
    """The natural HDR maps (.hdr, .exr) in `folder` (default `default_envmap_folder()`), sorted by
    name; empty if the folder does not exist."""
    folder = default_envmap_folder() if folder is None else Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in ENVMAP_SUFFIXES and p.is_file())


def resize_envmap(env: np.ndarray, height: int) -> np.ndarray:
    """(H, 2H, 3) -> (height, 2 height, 3): area averaging when shrinking (cv2.INTER_AREA, no
    aliasing of small bright sources), bilinear when enlarging."""
    if env.shape[0] == height:
        return env
    interp = cv2.INTER_AREA if height < env.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(env, (2 * height, height), interpolation=interp).astype(np.float32)


@functools.lru_cache(maxsize=64)
def _load_natural(path: str, height: int) -> np.ndarray:
    env = resize_envmap(read_envmap(path), height)
    env.setflags(write=False)  # shared by every caller: never modified in place
    return env


def load_natural_envmap(path: str | os.PathLike, height: int) -> np.ndarray:
    """A natural map read and resized to (height, 2 height, 3) float32; cached per (path, height)
    (the 1k HDRs take ~50 ms to read). The returned array is read-only and shared: copy to modify."""
    return _load_natural(str(Path(path).resolve()), int(height))


# ---------------------------------------------------------------------------------------------
# augmentation
# ---------------------------------------------------------------------------------------------

def rotate_envmap(env: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotate the environment about the up axis (+y) by `angle_deg`, right-handed
    (R_y(a): x' = x cos a + z sin a, z' = -x sin a + z cos a).

    The result E' satisfies E'(R_y(a) d) = E(d). Since R_y(a) sends azimuth u to u - a / 360, this
    is a circular shift of the columns by s = a / 360 * W texels: exact for whole-texel shifts (no
    resampling), linear interpolation between the two neighbouring shifts otherwise (a slight blur).
    """
    W = env.shape[1]
    s = (angle_deg / 360.0 * W) % W
    k = math.floor(s)
    t = s - k
    if t < 1e-6 or t > 1 - 1e-6:  # whole texels (up to float rounding of the angle)
        return np.roll(env, -int(round(s)) % W, axis=1)
    # E'[:, j] = E[:, j + s] = (1 - t) E[:, j + k] + t E[:, j + k + 1]
    return ((1 - t) * np.roll(env, -k, axis=1) + t * np.roll(env, -k - 1, axis=1)).astype(env.dtype)


def mirror_envmap(env: np.ndarray) -> np.ndarray:
    """Flip u: E'(-x, y, z) = E(x, y, z) -- a mirror through the y-z plane, which also flips the
    handedness of the scene (text reads backwards), harmless for training lighting.
    Texel-exact: column j goes to W - 1 - j, and u = (j + 1/2) / W goes to 1 - u."""
    return np.ascontiguousarray(env[:, ::-1])


@dataclass(frozen=True)
class EnvmapAugmentation:
    """One augmentation of a natural map, applied as mirror, then rotation, then colour.

    rotation_deg: about +y (see `rotate_envmap`). mirror: flip u first (x -> -x).
    exposure: overall radiance factor. white_balance: per-channel (R, G, B) gains with unit
    luminance (0.2126 R + 0.7152 G + 0.0722 B = 1), so brightness is set by exposure alone.
    Note: the dataset scales each image to a mean of ~0.5 and E by the same factor (DESIGN.md),
    which cancels exposure; it still matters for anything done before that normalization.
    """

    rotation_deg: float = 0.0
    mirror: bool = False
    exposure: float = 1.0
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @classmethod
    def sample(cls, rng: np.random.Generator, width: int | None = None, exposure_range=(0.5, 2.0),
               white_balance_spread: float = 0.1, p_mirror: float = 0.5) -> "EnvmapAugmentation":
        """A random augmentation: rotation uniform in [0, 360) (a whole number of texels when the
        map `width` is given, so rotation resamples nothing), mirror with p_mirror, exposure
        log-uniform in exposure_range, gains exp(U[-spread, spread]) rescaled to unit luminance."""
        if width is not None:
            rotation = float(rng.integers(width)) * 360.0 / width
        else:
            rotation = float(rng.uniform(0.0, 360.0))
        mirror = bool(rng.random() < p_mirror)
        lo, hi = np.log(exposure_range)
        exposure = float(np.exp(rng.uniform(lo, hi)))
        gains = np.exp(rng.uniform(-white_balance_spread, white_balance_spread, 3))
        gains /= LUMINANCE @ gains
        return cls(rotation, mirror, exposure, tuple(float(g) for g in gains))

    def apply(self, env: np.ndarray) -> np.ndarray:
        """(H, 2H, 3) float32 -> new (H, 2H, 3) float32 array (the input is not modified)."""
        out = mirror_envmap(env) if self.mirror else env
        out = rotate_envmap(out, self.rotation_deg)
        scale = (self.exposure * np.asarray(self.white_balance, dtype=np.float64)).astype(np.float32)
        return (out * scale).astype(np.float32)


def augment_envmap(env: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A randomly augmented copy of env (H, 2H, 3): rotation about +y by whole texels, mirroring,
    exposure and white balance (see `EnvmapAugmentation.sample`). To record what was done, use
    `EnvmapAugmentation.sample(rng, width)` and `.apply(env)` instead."""
    return EnvmapAugmentation.sample(rng, width=env.shape[1]).apply(env)


# ---------------------------------------------------------------------------------------------
# procedural maps
# ---------------------------------------------------------------------------------------------

def texel_directions(height: int) -> np.ndarray:
    """Unit directions (H, 2H, 3) float64 of the texels of an (H, 2H) map, world frame.

    Columns at u = (j + 1/2) / W, rows at v = i / (H - 1) (row 0 at +y, row H-1 at -y), matching
    `EnvironmentMap.lookup_uv`, so a texel's value is what a lookup in its direction returns."""
    W = 2 * height
    u = (np.arange(W) + 0.5) / W
    v = np.arange(height) / (height - 1)
    phi, theta = 2 * np.pi * u[None, :], np.pi * v[:, None]
    s = np.sin(theta)
    return np.stack(np.broadcast_arrays(s * np.sin(phi), np.cos(theta), -s * np.cos(phi)), axis=-1)


def _hsv(rng: np.random.Generator, sat=(0.0, 0.7), val=(0.2, 1.0), hue=None) -> np.ndarray:
    """A random RGB colour (3,) from HSV ranges."""
    h = rng.uniform(0, 1) if hue is None else hue
    s, v = rng.uniform(*sat), rng.uniform(*val)
    k = (np.array([5.0, 3.0, 1.0]) + h * 6) % 6
    return v - v * s * np.clip(np.minimum(k, 4 - k), 0, 1)


def _frame(rng: np.random.Generator) -> np.ndarray:
    """A random orthonormal frame (3, 3), rows e1, e2, e3."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q.T


def _matmul3(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """a (..., 3) @ m (3,) or (3, K) by broadcasting: numpy's @ calls BLAS, whose rounding can
    depend on the thread count, and a map must be bit-identical for its seed on any setting."""
    return a[..., 0:1] * m[0] + a[..., 1:2] * m[1] + a[..., 2:3] * m[2] if m.ndim == 2 else \
        a[..., 0] * m[0] + a[..., 1] * m[1] + a[..., 2] * m[2]


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _angle_to(d: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Angle (radians) between directions d (..., 3) and unit c (3,)."""
    return np.arccos(np.clip(_matmul3(d, c), -1.0, 1.0))


def _pattern(rng: np.random.Generator, d: np.ndarray) -> np.ndarray:
    """A random scalar texture in [0, 1] on the sphere, (...,) from directions (..., 3).

    Defined in direction space (no seam at u = 0 and no pinching at the poles). The base frequency
    is log-uniform in 1.5-12 cycles per radian: periods of 5-40 degrees, i.e. at least ~7 texels at
    the usual height 256 (no aliasing) and fine enough to show refraction's distortions."""
    kind = rng.choice(["checker", "stripes", "noise", "blobs", "tiles"])
    e = _frame(rng)
    p = _matmul3(d, e.T)  # coordinates in a random frame
    f = np.exp(rng.uniform(np.log(1.5), np.log(12.0))) * 2 * np.pi
    if kind == "checker":
        return (np.sin(f * p[..., 0]) * np.sin(f * p[..., 1]) * np.sin(f * p[..., 2] + rng.uniform(0, 6)) > 0
                ).astype(np.float64)
    if kind == "stripes":
        sharp = rng.uniform(1, 20)
        return 0.5 + 0.5 * np.tanh(sharp * np.sin(f * p[..., 0] + rng.uniform(0, 2 * np.pi)))
    if kind == "tiles":  # bright tiles separated by dark grout lines (bricks, windows, shelves)
        g = np.abs(np.sin(f * p[..., 0])) * np.abs(np.sin(0.5 * f * p[..., 1] + rng.uniform(0, 6)))
        return (g > rng.uniform(0.05, 0.3)).astype(np.float64)
    if kind == "noise":  # fractal sum of random plane waves, 4 octaves
        out = np.zeros(d.shape[:-1])
        for octave in range(4):
            w = rng.normal(size=(8, 3)) * (f / 8) * 2 ** octave
            out += np.sin(_matmul3(d, w.T) + rng.uniform(0, 2 * np.pi, 8)).sum(-1) * 0.5 ** octave
        return 0.5 + 0.5 * np.tanh(out / 3)
    # blobs: many small soft discs
    n = int(rng.integers(20, 120))
    centres = rng.normal(size=(n, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    radius = rng.uniform(0.03, 0.15, n)
    out = np.zeros(d.shape[:-1])
    for c, r in zip(centres, radius):  # a loop over blobs, each vectorized over all texels
        # soft edge between angles 0.7 r and r, on the cosine (no arccos per texel)
        out = np.maximum(out, _smoothstep(math.cos(r), math.cos(0.7 * r), _matmul3(d, c)))
    return out


def procedural_envmap(rng: np.random.Generator, height: int = 256) -> np.ndarray:
    """A random procedural environment map, (height, 2 height, 3) float32, linear, >= 0.

    Layers: a sky gradient (horizon -> zenith colour) over a ground colour; 1-5 textured regions
    (checker, stripes, tiles, fractal noise, blobs in spherical caps, bands or the ground); bright
    sources -- a sun (small disc, HDR intensity with a glow) and/or small lamps and rectangular
    area lights -- so there is always a strong directional light (max / median >~ 20).
    Mean sky radiance is ~1; only ratios matter (images are normalized).
    """
    d = texel_directions(height)
    y = d[..., 1]
    texel = np.pi / (height - 1)  # angular size of a texel along v

    zenith, horizon, ground = _hsv(rng, (0.0, 0.8)), _hsv(rng, (0.0, 0.4), (0.5, 1.0)), _hsv(rng, (0.0, 0.6), (0.1, 0.6))
    gamma = rng.uniform(0.3, 1.5)
    sky = horizon + (zenith - horizon) * (np.clip(y, 0, 1) ** gamma)[..., None]
    blend = _smoothstep(0.0, rng.uniform(0.01, 0.15), -y)[..., None]  # soft horizon line
    env = sky * (1 - blend) + ground * blend

    # textured regions: the texture is what refraction through glass distorts, so always some
    for _ in range(int(rng.integers(1, 6))):
        region = rng.choice(["cap", "band", "ground"])
        if region == "cap":
            c = rng.normal(size=3)
            c /= np.linalg.norm(c)
            radius = rng.uniform(0.3, 1.3)
            mask = _smoothstep(radius, radius - texel - rng.uniform(0, 0.1), _angle_to(d, c))
        elif region == "band":
            a = rng.normal(size=3)
            a /= np.linalg.norm(a)
            width = rng.uniform(0.1, 0.6)
            mask = _smoothstep(width, width - texel - rng.uniform(0, 0.05), np.abs(_matmul3(d, a) - rng.uniform(-0.5, 0.5)))
        else:
            mask = blend[..., 0]
        # one dark and one bright colour: contrast is what makes refracted texture informative
        c0, c1 = _hsv(rng, (0.0, 0.9), (0.03, 0.35)), _hsv(rng, (0.0, 0.9), (0.5, 1.0))
        if rng.random() < 0.5:
            c0, c1 = c1, c0
        tex = c0 + (c1 - c0) * _pattern(rng, d)[..., None]
        env = env + (tex - env) * (mask * rng.uniform(0.6, 1.0))[..., None]

    # bright sources, antialiased over about one texel
    sources = []
    if rng.random() < 0.7:  # sun: above the horizon, 0.5-3 deg radius, 100-5000x the sky
        el, az = rng.uniform(0.05, 1.4), rng.uniform(0, 2 * np.pi)
        c = np.array([np.cos(el) * np.sin(az), np.sin(el), -np.cos(el) * np.cos(az)])
        r = max(np.radians(rng.uniform(0.5, 3.0)), texel)
        ang = _angle_to(d, c)
        disc = _smoothstep(r + texel, r, ang)
        glow = np.exp(-ang / rng.uniform(0.05, 0.3)) * rng.uniform(1, 10)
        sources.append(_hsv(rng, (0.0, 0.3), (0.9, 1.0)) * (disc * np.exp(rng.uniform(np.log(100), np.log(5000)))
                                                            + glow)[..., None])
    for _ in range(int(rng.integers(0 if sources else 1, 5))):  # lamps: 1-6 deg, 20-300x
        c = rng.normal(size=3)
        c /= np.linalg.norm(c)
        r = max(np.radians(rng.uniform(1.0, 6.0)), texel)
        disc = _smoothstep(r + texel, r, _angle_to(d, c))
        sources.append(_hsv(rng, (0.0, 0.5), (0.8, 1.0)) * (disc * np.exp(rng.uniform(np.log(20), np.log(300))))[..., None])
    for _ in range(int(rng.integers(0, 3))):  # area lights (windows, panels): 5-25 deg, 5-50x
        e = _frame(rng)
        p = _matmul3(d, e.T)
        half = np.radians(rng.uniform(5, 25, 2))
        rect = (_smoothstep(np.sin(half[0]) + texel, np.sin(half[0]), np.abs(p[..., 0]))
                * _smoothstep(np.sin(half[1]) + texel, np.sin(half[1]), np.abs(p[..., 1])) * (p[..., 2] > 0))
        sources.append(_hsv(rng, (0.0, 0.3), (0.8, 1.0)) * (rect * rng.uniform(5, 50))[..., None])
    for s in sources:
        env = env + s
    return np.maximum(env, 0.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# the pool
# ---------------------------------------------------------------------------------------------

def envmap_from_description(desc: dict, folder: str | os.PathLike | None = None, height: int = 256) -> np.ndarray:
    """Regenerate a map from the description an `EnvmapSampler` gave with it, (H, 2H, 3) float32.

    {"source": "procedural", "seed": s} -> procedural_envmap(default_rng(s), height).
    {"source": "natural", "name": file name in folder, "rotation_deg", "mirror", "exposure",
    "white_balance"} -> the natural map resized to height, then the augmentation.
    Identical to the original when height is the same (rotation is whole texels at that height).
    """
    source = desc.get("source")
    if source == "procedural":
        return procedural_envmap(np.random.default_rng(int(desc["seed"])), height)
    if source == "natural":
        folder = default_envmap_folder() if folder is None else Path(folder)
        path = folder / desc["name"]
        if not path.is_file():
            raise LookingGlassError(f"environment map '{desc['name']}' of the description is not in the folder", folder)
        aug = EnvmapAugmentation(float(desc.get("rotation_deg", 0.0)), bool(desc.get("mirror", False)),
                                 float(desc.get("exposure", 1.0)),
                                 tuple(float(g) for g in desc.get("white_balance", (1.0, 1.0, 1.0))))
        return aug.apply(load_natural_envmap(path, height))
    raise LookingGlassError(f"unknown environment map source {source!r} (use 'natural' or 'procedural')")


class EnvmapSampler:
    """Deterministic stream of (envmap (H, 2H, 3) float32, description dict) pairs.

    Item i depends only on (seed, i) -- numpy Generator seeded with [seed, i] -- so scenes can be
    generated in any order or in parallel and still get the same maps. With probability
    p_procedural an item is a procedural map, else a random natural map (from `names` if given,
    e.g. to keep train and test maps apart, as the paper does) with a random augmentation.
    """

    def __init__(self, folder: str | os.PathLike | None = None, height: int = 256, p_procedural: float = 0.5,
                 seed: int = 0, names: list[str] | None = None, augment: bool = True):
        self.folder = default_envmap_folder() if folder is None else Path(folder)
        self.height = int(height)
        self.p_procedural = float(p_procedural)
        self.seed = int(seed)
        self.augment = augment
        paths = natural_envmaps(self.folder)
        if names is not None:
            wanted = set(names)
            paths = [p for p in paths if p.name in wanted or p.stem in wanted]
            missing = wanted - {p.name for p in paths} - {p.stem for p in paths}
            if missing:
                raise LookingGlassError(f"environment maps not found: {sorted(missing)}", self.folder)
        self.paths = paths
        if not self.paths and self.p_procedural < 1.0:
            raise LookingGlassError("no natural environment maps (.hdr/.exr) found; "
                                    "give a folder or set p_procedural=1", self.folder)

    def description(self, index: int) -> dict:
        """The description of item `index` (cheap: nothing is loaded or drawn)."""
        rng = np.random.default_rng([self.seed, int(index)])
        if rng.random() < self.p_procedural:
            return {"source": "procedural", "seed": int(rng.integers(2**62))}
        path = self.paths[int(rng.integers(len(self.paths)))]
        aug = EnvmapAugmentation.sample(rng, width=2 * self.height) if self.augment else EnvmapAugmentation()
        d = asdict(aug)
        d["white_balance"] = list(d["white_balance"])
        return {"source": "natural", "name": path.name, **d}

    def sample(self, index: int) -> tuple[np.ndarray, dict]:
        """(envmap (H, 2H, 3) float32, description) of item `index`."""
        desc = self.description(index)
        return envmap_from_description(desc, self.folder, self.height), desc

    __getitem__ = sample

    def __iter__(self) -> Iterator[tuple[np.ndarray, dict]]:
        """Items 0, 1, 2, ... without end."""
        return (self.sample(i) for i in itertools.count())
