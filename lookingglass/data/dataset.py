"""Synthetic training data on disk: `lookingglass generate` (issue #3, item 4).

One scene = a random procedural glass shape (`shapes.random_shape`), an environment map from the
pool (`envmaps.EnvmapSampler`), the paper's camera rig (`rigs.paper_rig_params`), the rendered
images and ground-truth two-bounce maps (`render.tracer.render_views`), the visual hull carved from
the rendered masks (`hull.carve_visual_hull`) and the hull's own two-bounce maps
(`render.tracer.trace_two_bounce`): everything the normal and point networks train on.

Layout (DIR/SPLIT/...):

    config.json              {"format", "split", "seed", "views", "config": DatasetConfig}
    scene_00000/
        maps.npz             np.savez_compressed, no object arrays (np.load(allow_pickle=False)):
            image   (V, H, W, 3) float16  linear radiance in the environment map's units,
                                          *not* normalized (clipped at 65504, float16's max)
            mask    (V, H, W)    bool     the object covers the pixel centre
            n1, n2  (V, H, W, 3) float16  GT normals at the first / second hit, camera frame
                                          (x right, y up, z towards the camera), outward, 0 where
                                          the hit does not exist
            valid   (V, H, W)    bool     the two-bounce model explains the pixel (TwoBounce.valid)
            tir     (V, H, W)    bool     total internal reflection at the second hit
            vh_mask, vh_n1, vh_n2, vh_valid, vh_tir: the same for the visual hull
        mesh.ply             ground truth, world frame = unit-sphere frame (binary PLY, float32)
        hull.npz             visual hull, the same world frame: vertices (N, 3) float32, faces
                             (F, 3) int32, compressed (LS3-subdivided hulls have ~100k faces: a PLY
                             would take 2 MB, this 0.8 MB; `load_scene_mesh(dir, "hull")` reads it)
        meta.json            cameras (look-at origin/target/up, fov_x_deg, width, height), the
                             environment map's description (`envmaps.envmap_from_description`
                             regenerates the pixels), seeds, hull frame and coverage, timings.
                             Written last, atomically: a scene is finished iff meta.json exists.

Rendering happens directly at the network's resolution (cpu preset 128 x 96, paper preset
256 x 192, DESIGN.md): the image is anti-aliased by s x s stratified samples per pixel (a box
filter, the same as area-downsampling a larger render), the two-bounce maps are taken at the pixel
centres, exactly as the pipeline traces the hull's maps at the network's resolution
(`normals.inputs.NormalInputs.from_capture`). The environment map is rendered at the height the dataset
serves it at (cpu 128 x 256, paper 256 x 512), so image and E agree exactly.

Determinism: scene i is a function of (seed, split, i) alone -- its seeds come from
`np.random.SeedSequence(seed, spawn_key=(split code, i))` -- and every scene is made with one
torch thread and one Embree thread, so any order, worker count or sharding writes identical
arrays (on one software stack: another Embree or torch build may round differently).

train and test draw from disjoint seed streams, and the natural environment maps are split too:
`DatasetConfig.test_envmaps` (2 of the 9: forest_slope, potsdamer_platz) light only test scenes,
the other 7 only training scenes, as the paper keeps its test maps apart; procedural maps (half
of the scenes, `p_procedural`) come from each split's own seed stream.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import time
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..configio import check_ranges, setting
from ..errors import ConfigError, LookingGlassError
from ..config import HullConfig
from ..physics.constants import (IOR_AIR, IOR_GLASS, IOR_MAX, IOR_MIN, PAPER_RENDER_FOV_X_DEG as PAPER_FOV_X_DEG,
                                 check_ior_range)
from ..parallel import map_in_processes, run_and_collect, worker_count
from .shape_config import ShapeConfig

if TYPE_CHECKING:
    import trimesh

FORMAT_VERSION = 1
SPLITS = {"train": 0, "test": 1}
RIG_VIEWS = (5, 10, 20)
FLOAT16_MAX = 65504.0
MAP_KEYS = ("image", "mask", "n1", "n2", "valid", "tir", "vh_mask", "vh_n1", "vh_n2", "vh_valid", "vh_tir")
SCENE_FILES = ("maps.npz", "mesh.ply", "hull.npz", "meta.json")
MAX_ATTEMPTS = 4


@dataclass
class DatasetConfig:
    """What a scene looks like; saved as DIR/SPLIT/config.json. Plain fields (JSON-able).

    preset: the name of the preset (lookingglass.presets) the config started from, recorded.
    width, height: rendered (= stored = network) image size. fov_x_deg: horizontal field of view.
    envmap_height: the environment map is rendered and served at envmap_height x 2 envmap_height.
    samples_per_axis: anti-aliasing, s x s stratified jittered samples per pixel.
    max_depth, prune_threshold: light transport (see `render.tracer.RenderConfig`).
    ior_range: the glass's index of refraction (LO, HI): LO == HI (the default, DESIGN.md's glass)
        every scene's; LO < HI each scene's drawn uniformly in it (`scene_ior`, meta.json's "ior").
    ior_per_shape: K; scene k shows the shape, rig, environment map and render seed of scene k // K
        (of the same seed and split) with its own IoR draw: K IoRs per shape, as the paper's
        variable-IoR test set (its supplement: 5 IoRs in [1.3, 1.7] per test shape).
    ext_ior: air (DESIGN.md).
    p_procedural: chance that a scene's map is procedural rather than an augmented natural one.
    test_envmaps: natural maps (file names) kept for the test split; training uses the others.
    family_weights: relative frequency of the shape families (families.FAMILIES order: procedural,
        cad, handle, thin, blob); the default makes only procedural shapes, as the shipped splits.
    hull_mask_scale: the hull is carved from masks rendered at s x (width, height), s drawn
        log-uniformly from this range per scene: users' hulls come from full-resolution masks
        (480x360 is 3.75), so a net trained on 128x96 hulls only never saw a good one. The network
        inputs stay at width x height (`reconstruct` resizes photos to that size too).
    hull: visual hull settings (its num_threads is overridden: one thread per worker).
    shape: the procedural shape distribution.
    """

    preset: str = "cpu"
    width: int = setting(128, "Rendered (= stored = network) image width.", range=(8, None))
    height: int = setting(96, "Rendered image height.", range=(8, None))
    fov_x_deg: float = setting(PAPER_FOV_X_DEG, "Horizontal field of view (degrees).", range=(1, 179))
    envmap_height: int = setting(128, "The environment map's height (its width: twice that).", range=(4, None))
    samples_per_axis: int = setting(2, "Anti-aliasing: s x s jittered samples a pixel.", range=(1, None))
    max_depth: int = setting(64, "Most interfaces a light path crosses.", range=(1, None))
    prune_threshold: float = setting(1e-3, "Light branches whose throughput falls below this are dropped.",
                                     range=(0, None))
    ior_range: tuple[float, float] = setting(  # checked by check_ior_range, the bounds in the help
        (IOR_GLASS, IOR_GLASS), f"The glass's index of refraction LO HI, from {IOR_MIN} to {IOR_MAX}: LO = HI every "
        "scene's, LO < HI each scene's drawn uniformly in it.")
    ior_per_shape: int = setting(1, "K: scene k shows the shape, rig and map of scene k // K with its own IoR draw.",
                                 range=(1, None))
    ext_ior: float = setting(IOR_AIR, "Index of refraction around the glass.", range=(1, None))
    p_procedural: float = setting(0.5, "Chance that a scene's environment map is procedural.", range=(0, 1))
    test_envmaps: tuple[str, ...] = ("forest_slope_1k.hdr", "potsdamer_platz_1k.hdr")
    family_weights: tuple[float, float, float, float, float] = setting(
        (1.0, 0.0, 0.0, 0.0, 0.0), "Relative frequency of the shape families procedural, cad, handle, thin, blob.",
        range=(0, None))
    hull_mask_scale: tuple[float, float] = setting(
        (1.0, 1.0), "The hull is carved from masks at s x the image size, s log-uniform in LO HI.", range=(1, 64))
    hull: HullConfig = field(default_factory=HullConfig)
    shape: ShapeConfig = field(default_factory=ShapeConfig)

    def __post_init__(self) -> None:
        check_ranges(self)
        if sum(self.family_weights) <= 0:
            raise ConfigError("family_weights: at least one family needs a positive weight")
        if self.hull_mask_scale[0] > self.hull_mask_scale[1]:
            raise ConfigError(f"hull_mask_scale: LO must be <= HI, got {self.hull_mask_scale}")
        check_ior_range(self.ior_range, "ior_range", ConfigError, equal_ok=True)

    def to_dict(self) -> dict:
        """JSON-normalized dict (tuples as lists), the form config.json holds."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: dict) -> "DatasetConfig":
        """The config a config.json holds; one written before `ior_range` has its single "ior"
        (read as the range of that one value) and lacks the keys added since (their defaults)."""
        from ..configio import config_from_dict

        if isinstance(data, dict) and "ior" in data and "ior_range" not in data:
            data = {**{k: v for k, v in data.items() if k != "ior"}, "ior_range": [data["ior"], data["ior"]]}
        return config_from_dict(cls, data, where="dataset config")


# ---------------------------------------------------------------------------------------------
# arguments
# ---------------------------------------------------------------------------------------------
def parse_shard(text: str) -> tuple[int, int]:
    """"K/N" -> (K, N) with 1 <= K <= N; scenes i with i % N == K - 1 belong to shard K."""
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(text))
    if not m:
        raise LookingGlassError(f"--shard must look like K/N (e.g. 2/8), got {text!r}")
    k, n = int(m.group(1)), int(m.group(2))
    if n < 1 or not 1 <= k <= n:
        raise LookingGlassError(f"--shard K/N needs 1 <= K <= N (K counts from 1), got {text!r}")
    return k, n


MAX_SCENES = 1_000_000  # a split's scene count at most (a typo of 1e9 would list every index first)


def _check_args(scenes: int, views: int, split: str, shard: tuple[int, int], workers: int | None,
                seed: int = 0) -> None:
    if seed < 0:
        raise LookingGlassError(f"--seed must be >= 0, got {seed}")
    if not 1 <= scenes <= MAX_SCENES:
        raise LookingGlassError(f"--scenes must be from 1 to {MAX_SCENES}, got {scenes}")
    if views not in RIG_VIEWS:
        raise LookingGlassError(f"--views must be 5, 10 or 20 (the paper's rigs), got {views}")
    if split not in SPLITS:
        raise LookingGlassError(f"--split must be train or test, got {split!r}")
    k, n = shard
    if n < 1 or not 1 <= k <= n:
        raise LookingGlassError(f"shard {k}/{n}: need 1 <= K <= N")
    if workers is not None and workers < 0:
        raise LookingGlassError(f"--workers must be >= 0 (0: one per CPU core), got {workers}")


def rig_subset(stored_views: int, views: int) -> list[int]:
    """Indices of the `views`-view paper rig inside the `stored_views`-view one (the rigs are
    nested, 5 in 10 in 20: `rigs.py`), in the smaller rig's order. E.g. (10, 5) -> [0, 6, 2, 8, 4]."""
    from .rigs import rig_layout

    if views not in RIG_VIEWS or stored_views not in RIG_VIEWS or views > stored_views:
        raise LookingGlassError(f"cannot take a {views}-view rig out of {stored_views} views "
                                f"(rigs have 5, 10 or 20 views; at most the stored number)")
    big = list(zip(*rig_layout(stored_views)[:2]))
    return [big.index(a) for a in zip(*rig_layout(views)[:2])]


def scene_name(index: int) -> str:
    return f"scene_{index:05d}"


def scene_seeds(seed: int, split: str, index: int, attempt: int = 0) -> dict[str, int]:
    """The seeds of scene `index`: a function of (seed, split, index, attempt) only.
    attempt > 0 redraws a scene whose first draw failed (a degenerate shape or hull)."""
    key = (SPLITS[split], int(index)) + ((int(attempt),) if attempt else ())
    s = np.random.SeedSequence(int(seed), spawn_key=key).generate_state(4, dtype=np.uint64)
    s = [int(x >> np.uint64(1)) for x in s]  # 63-bit: fits every consumer (numpy, int64)
    return {"shape": s[0], "rig": s[1], "envmap": s[2], "render": s[3] & 0xFFFFFFFF}


FAMILY_EDGE = 0.05  # longest edge of a training CSG shape (unit sphere): ~1.5 px at 128x96


def scene_draws(seeds: dict[str, int], config: DatasetConfig) -> tuple[str, float]:
    """Scene's shape family and hull-mask scale (see DatasetConfig). The default config draws
    nothing (procedural, 1.0), so scenes of the shipped splits are what they were."""
    from .families import FAMILIES

    weights = np.asarray(config.family_weights, float)
    lo, hi = config.hull_mask_scale
    if weights[1:].sum() == 0 and lo == hi:
        return "procedural", float(lo)
    rng = np.random.default_rng([seeds["shape"], 7])  # its own stream: the shape's is untouched
    family = FAMILIES[int(rng.choice(len(FAMILIES), p=weights / weights.sum()))]
    scale = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    return family, round(scale, 3)


def scene_ior(seed: int, split: str, index: int, config: DatasetConfig) -> float:
    """Scene `index`'s index of refraction: config.ior_range's one value, or a uniform draw in it
    (to 1e-4) from a stream of its own, keyed by the scene's own index (not its shape's, so the
    `ior_per_shape` scenes of one shape differ) and not by the attempt (a redrawn shape keeps it)."""
    lo, hi = config.ior_range
    if lo == hi:
        return float(lo)
    rng = np.random.default_rng([scene_seeds(seed, split, index)["shape"], 11])  # 11: its own stream
    return round(float(rng.uniform(lo, hi)), 4)


def split_envmap_names(config: DatasetConfig, split: str, folder=None) -> list[str] | None:
    """Natural map names a split may use: test -> config.test_envmaps, train -> the others.
    None when the folder has no natural maps (the sampler then errors unless p_procedural = 1)."""
    from .envmaps import natural_envmaps

    names = [p.name for p in natural_envmaps(folder)]
    if not names:
        return None
    held = set(config.test_envmaps)
    chosen = [n for n in names if (n in held) == (split == "test")]
    if not chosen and config.p_procedural < 1:
        raise LookingGlassError(f"no natural environment maps left for the {split} split "
                                f"(test_envmaps = {list(config.test_envmaps)})")
    return chosen


# ---------------------------------------------------------------------------------------------
# one scene
# ---------------------------------------------------------------------------------------------
@dataclass
class SceneData:
    """A generated scene in memory: `maps` (MAP_KEYS, the stored dtypes), the meshes, meta."""

    maps: dict[str, np.ndarray]
    mesh: "trimesh.Trimesh"
    hull: "trimesh.Trimesh"
    meta: dict


def _f16(x) -> np.ndarray:
    a = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, dtype=np.float32)
    return np.clip(a, -FLOAT16_MAX, FLOAT16_MAX).astype(np.float16)


def _bool(x) -> np.ndarray:
    return np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, dtype=bool)


def _float32_vertices(mesh):
    """Round the vertices to float32 -- what the PLY file stores -- so the stored mesh is exactly
    the one rendered and traced."""
    mesh.vertices = np.asarray(mesh.vertices, dtype=np.float32).astype(np.float64)
    return mesh


def make_scene(index: int, split: str, seed: int, views: int, config: DatasetConfig,
               envmap_folder=None, attempt: int = 0) -> SceneData:
    """Generate scene `index` of a split in memory (single-threaded: one torch and one Embree
    thread). Raises on a degenerate draw; `generate_scene` retries with the next attempt."""
    import torch

    from ..physics.camera import Cameras
    from ..physics.environment import EnvironmentMap
    from ..render.tracer import RenderConfig, render_views, trace_two_bounce
    from ..threads import torch_threads
    from .envmaps import EnvmapSampler
    from .rigs import paper_rig_params
    from ..hull import carve_visual_hull
    from ..render.raycast import object_masks
    from .families import random_family_shape
    from .shapes import random_shape, shape_stats

    shape_index = index // config.ior_per_shape  # the scene whose shape, rig, map and render seed this one shows
    seeds = scene_seeds(seed, split, shape_index, attempt)
    ior = scene_ior(seed, split, index, config)
    timings: dict[str, float] = {}
    clock = [time.perf_counter()]

    def lap(name: str) -> None:
        now = time.perf_counter()
        timings[name] = round(now - clock[0], 4)
        clock[0] = now

    with torch_threads(1), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        family, mask_scale = scene_draws(seeds, config)
        if family == "procedural":
            mesh = random_shape(seeds["shape"], config.shape)
        else:
            mesh = random_family_shape(family, seeds["shape"], max_edge=FAMILY_EDGE)
        mesh = _float32_vertices(mesh)
        lap("shape")
        sampler = EnvmapSampler(envmap_folder, config.envmap_height, config.p_procedural, seed=seeds["envmap"],
                                names=split_envmap_names(config, split, envmap_folder))
        env, env_desc = sampler.sample(0)
        lap("envmap")
        rig = paper_rig_params(views, np.random.default_rng(seeds["rig"]))
        cams = Cameras.look_at(rig["origin"], rig["target"], rig["up"], config.fov_x_deg,
                               config.width, config.height)
        rcfg = RenderConfig(ior=ior, ext_ior=config.ext_ior, max_depth=config.max_depth,
                            samples_per_axis=config.samples_per_axis, seed=seeds["render"],
                            prune_threshold=config.prune_threshold, threads=1)
        res = render_views(mesh, EnvironmentMap(torch.from_numpy(np.ascontiguousarray(env))), cams, rcfg)
        lap("render")
        timings["render_two_bounce"] = round(res.stats.seconds_two_bounce, 4)
        hcfg = dataclasses.replace(config.hull, num_threads=1)
        hull_masks, hull_cams = res.mask, cams
        if mask_scale != 1.0:  # carve from sharper masks, as `reconstruct` does from a photo's own
            hull_cams = Cameras.look_at(rig["origin"], rig["target"], rig["up"], config.fov_x_deg,
                                        round(config.width * mask_scale), round(config.height * mask_scale))
            hull_masks = object_masks(mesh, hull_cams)
            lap("hull_masks")
        vh = carve_visual_hull(hull_masks, hull_cams, hcfg)
        hull = _float32_vertices(vh.mesh)
        lap("hull")
        tb = trace_two_bounce(hull, cams, ior, config.ext_ior, threads=1)
        lap("hull_two_bounce")

    image = res.image.numpy()
    maps = {
        "image": _f16(image), "mask": _bool(res.mask), "n1": _f16(res.normal1), "n2": _f16(res.normal2),
        "valid": _bool(res.two_bounce_valid), "tir": _bool(res.tir),
        "vh_mask": _bool(tb.mask), "vh_n1": _f16(tb.normal1), "vh_n2": _f16(tb.normal2),
        "vh_valid": _bool(tb.valid), "vh_tir": _bool(tb.tir),
    }
    meta = {
        "format": FORMAT_VERSION, "index": int(index), "split": split, "dataset_seed": int(seed),
        "attempt": int(attempt), "seeds": seeds, "views": int(views),
        **({"shape_index": shape_index} if config.ior_per_shape > 1 else {}),  # the shipped splits' meta as it was
        "width": config.width, "height": config.height, "ior": ior, "ext_ior": config.ext_ior,
        "cameras": {"origin": rig["origin"].tolist(), "target": rig["target"].tolist(), "up": rig["up"].tolist(),
                    "fov_x_deg": [float(config.fov_x_deg)] * views,
                    "polar_deg": rig["polar_deg"].tolist(), "azimuth_deg": rig["azimuth_deg"].tolist()},
        "envmap": env_desc, "envmap_height": config.envmap_height,
        "shape": {**shape_stats(mesh), "family": family},
        "hull_mask_size": [round(config.width * mask_scale), round(config.height * mask_scale)],
        "hull": {"faces": int(len(hull.faces)), "center": vh.center.tolist(), "scale": float(vh.scale),
                 "voxel_size": float(vh.voxel_size), "view_coverage": vh.view_coverage.tolist()},
        "stats": {"object_pixels": int(maps["mask"].sum()), "valid_pixels": int(maps["valid"].sum()),
                  "tir_pixels": int(maps["tir"].sum()),
                  "clipped_pixels": int((image > FLOAT16_MAX).any(-1).sum()),
                  "image_mean": float(image.astype(np.float64).mean())},
        "warnings": sorted({str(w.message) for w in caught}),
        "timings": timings,
    }
    return SceneData(maps, mesh, hull, meta)


def write_scene(scene_dir: Path, data: SceneData) -> dict:
    """Write a scene's files, meta.json last (each atomically). Returns meta (with write time
    and file sizes added)."""
    from ..fileio import write_atomic, write_json

    t0 = time.perf_counter()
    scene_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(scene_dir / "maps.npz", lambda p: np.savez_compressed(p, **data.maps))
    write_atomic(scene_dir / "mesh.ply", lambda p: data.mesh.export(p, file_type="ply", vertex_normal=False))
    hull_v = np.asarray(data.hull.vertices, dtype=np.float32)
    hull_f = np.asarray(data.hull.faces, dtype=np.int32)
    write_atomic(scene_dir / "hull.npz", lambda p: np.savez_compressed(p, vertices=hull_v, faces=hull_f))
    meta = dict(data.meta)
    meta["timings"] = {**meta["timings"], "write": round(time.perf_counter() - t0, 4)}
    meta["files"] = {n: (scene_dir / n).stat().st_size for n in SCENE_FILES[:-1]}
    write_json(scene_dir / "meta.json", meta)
    return meta


def is_finished(scene_dir: Path, index: int | None = None) -> bool:
    """A scene is finished when its meta.json (written last) parses, names the scene and every
    data file is there."""
    try:
        meta = json.loads((scene_dir / "meta.json").read_text())
    except (OSError, ValueError):
        return False
    if meta.get("format") != FORMAT_VERSION or (index is not None and meta.get("index") != index):
        return False
    return all((scene_dir / n).is_file() for n in SCENE_FILES)


def generate_scene(split_dir: Path, index: int, split: str, seed: int, views: int, config: DatasetConfig,
                   envmap_folder=None) -> dict | None:
    """Make and write scene `index` unless it is finished. Returns its meta, or None if skipped."""
    scene_dir = Path(split_dir) / scene_name(index)
    if is_finished(scene_dir, index):
        return None
    if scene_dir.exists():  # half-written: start over
        shutil.rmtree(scene_dir)
    errors = []
    for attempt in range(MAX_ATTEMPTS):
        try:
            data = make_scene(index, split, seed, views, config, envmap_folder, attempt)
        except (LookingGlassError, RuntimeError, ValueError) as exc:  # degenerate shape or hull
            errors.append(f"attempt {attempt}: {type(exc).__name__}: {exc}")
            continue
        return write_scene(scene_dir, data)
    raise RuntimeError(f"scene {index} of {split}: every draw failed ({'; '.join(errors)})")


# ---------------------------------------------------------------------------------------------
# the whole split
# ---------------------------------------------------------------------------------------------
def _split_config(split: str, seed: int, views: int, config: DatasetConfig) -> dict:
    return {"format": FORMAT_VERSION, "split": split, "seed": int(seed), "views": int(views),
            "config": config.to_dict()}


def _diff_keys(a, b, prefix="") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff_keys(a.get(k), b.get(k), f"{prefix}{k}.")
        return out
    return [] if a == b else [prefix.rstrip(".")]


def _as_read(saved: dict) -> dict:
    """A split's config.json as this version reads it: a config written before a key existed (or
    before `ior_range` replaced "ior") compares as that key's default, so its folder still resumes."""
    try:
        config = DatasetConfig.from_dict(saved["config"]).to_dict()
    except (KeyError, TypeError, ValueError, LookingGlassError):
        return saved  # not a config this version reads: compared as it is, the difference is reported
    return {**saved, "config": config}


def prepare_split_dir(out, split: str, seed: int, views: int, config: DatasetConfig) -> Path:
    """Create OUT/SPLIT with its config.json, or check that an existing one matches."""
    from ..fileio import write_json

    if Path(out).exists() and not Path(out).is_dir():
        raise LookingGlassError("the dataset folder exists and is not a folder", out)
    split_dir = Path(out) / split
    wanted = _split_config(split, seed, views, config)
    path = split_dir / "config.json"
    if path.exists():
        try:
            saved = json.loads(path.read_text())
        except ValueError:
            raise LookingGlassError("cannot parse the dataset config; remove it or use another --out", path) from None
        diff = _diff_keys(_as_read(saved), wanted)
        if diff:
            raise LookingGlassError(
                f"this folder holds scenes made with other settings (differs in: {', '.join(diff[:8])}"
                f"{' ...' if len(diff) > 8 else ''}); resume with the same --preset/--views/--seed or use "
                f"another --out", path)
    else:
        split_dir.mkdir(parents=True, exist_ok=True)
        write_json(path, wanted)
    return split_dir


def _check_envmaps(config: DatasetConfig, split: str, folder) -> None:
    """Fail early (before any worker starts) when the split's environment maps are missing."""
    from .envmaps import EnvmapSampler

    EnvmapSampler(folder, config.envmap_height, config.p_procedural, names=split_envmap_names(config, split, folder))


def _worker(task: tuple) -> tuple[int, dict | None]:
    split_dir, index, split, seed, views, config, folder = task
    return index, generate_scene(Path(split_dir), index, split, seed, views, config, folder)


def generate_dataset(out, scenes: int, views: int = 10, split: str = "train", seed: int = 0,
                     config: DatasetConfig | None = None, workers: int | None = 1,
                     shard: tuple[int, int] = (1, 1), reporter=None, envmap_folder=None) -> dict:
    """Write scenes 0..scenes-1 of `split` (those of `shard` K/N: i % N == K - 1) into OUT/SPLIT.

    Finished scenes are skipped, half-written ones redone. workers: processes (spawned, one
    torch / Embree thread each); None or 0 = one per CPU core. Returns a summary dict:
    {"split_dir", "scenes" (indices of this shard), "made", "skipped", "seconds", "timings"
    (mean seconds per part over the scenes made)}.
    """
    from ..progress import Reporter

    config = config or DatasetConfig()
    _check_args(scenes, views, split, shard, workers, seed)
    if envmap_folder is None:
        from .envmaps import default_envmap_folder

        envmap_folder = default_envmap_folder()
    _check_envmaps(config, split, envmap_folder)
    reporter = reporter or Reporter(quiet=True)
    split_dir = prepare_split_dir(out, split, seed, views, config)
    k, n = shard
    mine = [i for i in range(scenes) if i % n == k - 1]
    todo = [i for i in mine if not is_finished(split_dir / scene_name(i), i)]
    skipped = len(mine) - len(todo)
    if skipped:
        reporter.info(f"{skipped} of {len(mine)} scenes already finished in {split_dir}")
    workers = worker_count(workers, len(todo))
    tasks = [(str(split_dir), i, split, seed, views, config, str(envmap_folder)) for i in todo]
    metas: list[dict] = []
    start = time.perf_counter()
    desc = f"{split} scenes" + (f" (shard {k}/{n})" if n > 1 else "")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # recorded per scene in meta.json instead
        results = ((run_and_collect(_worker, t) for t in tasks) if workers == 1 else
                   map_in_processes(_worker, tasks, workers))
        for _, meta in reporter.track(results, total=len(tasks), description=desc):
            if meta:
                metas.append(meta)
    seconds = time.perf_counter() - start
    parts = sorted({p for m in metas for p in m["timings"]})
    timings = {p: float(np.mean([m["timings"].get(p, 0.0) for m in metas])) for p in parts}
    return {"split_dir": str(split_dir), "scenes": mine, "made": sorted(m["index"] for m in metas),
            "skipped": skipped, "seconds": seconds, "workers": workers, "timings": timings}


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------
def load_maps(scene_dir) -> dict[str, np.ndarray]:
    """The arrays of maps.npz (stored dtypes), read without unpickling."""
    path = Path(scene_dir) / "maps.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # a truncated file is not a zip
        raise LookingGlassError(f"cannot read scene maps ({exc}); re-run `lookingglass generate` with the same "
                                "options to remake the scene", path) from None


def load_scene_meta(scene_dir) -> dict:
    path = Path(scene_dir) / "meta.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise LookingGlassError(f"cannot read scene meta ({exc})", path) from None


def load_scene_mesh(scene_dir, which: str = "mesh"):
    """The ground truth ("mesh") or the visual hull ("hull") as trimesh.Trimesh, world frame,
    exactly as stored (no vertex merging)."""
    import trimesh

    if which == "mesh":
        path = Path(scene_dir) / "mesh.ply"
        if not path.is_file():
            raise LookingGlassError("ground-truth mesh not found", path)
        return trimesh.load(path, file_type="ply", process=False, force="mesh")
    if which == "hull":
        path = Path(scene_dir) / "hull.npz"
        try:
            with np.load(path, allow_pickle=False) as z:
                v, f = z["vertices"].astype(np.float64), z["faces"].astype(np.int64)
        except (OSError, ValueError, KeyError) as exc:
            raise LookingGlassError(f"cannot read the visual hull ({exc})", path) from None
        return trimesh.Trimesh(v, f, process=False, validate=False)
    raise ValueError(f'which must be "mesh" or "hull", not {which!r}')


def scene_cameras(meta: dict, dtype=None):
    """The scene's `Cameras` (V views of meta width x height) from meta.json."""
    import torch

    from ..physics.camera import Cameras

    c = meta["cameras"]
    return Cameras.look_at(c["origin"], c["target"], c["up"], c["fov_x_deg"], meta["width"], meta["height"],
                           dtype=dtype or torch.float32)


__all__ = ["DatasetConfig", "SceneData", "generate_dataset", "generate_scene", "make_scene", "write_scene",
           "parse_shard", "rig_subset", "scene_seeds", "scene_name", "is_finished", "load_maps", "load_scene_meta",
           "load_scene_mesh", "scene_cameras", "scene_ior", "split_envmap_names"]
