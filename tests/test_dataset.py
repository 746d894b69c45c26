"""Dataset generation (lookingglass generate) and the torch Dataset that reads it.

Tiny scenes (64 x 48, 5 views, a 64^3 hull) keep the whole file to a few tens of seconds.
"""

import dataclasses
import json
import shutil
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import torch
import trimesh
from trimesh.ray.ray_triangle import RayMeshIntersector

from lookingglass.data.dataset import (MAP_KEYS, SCENE_FILES, DatasetConfig, generate_dataset, load_maps,
                                       load_scene_mesh, load_scene_meta, parse_shard, rig_subset, scene_seeds)
from lookingglass.data.envmaps import envmap_from_description
from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.errors import LookingGlassError
from lookingglass.hull import HullConfig

SCENES, VIEWS, SEED = 4, 5, 3
TINY = DatasetConfig(preset="tiny", width=64, height=48, envmap_height=32, samples_per_axis=1,
                     hull=HullConfig(resolution=64, coarse_resolution=32, subdivision_iterations=3))


def scene(root, i, split="train"):
    return root / split / f"scene_{i:05d}"


def assert_same_scene(a, b):
    ma, mb = load_maps(a), load_maps(b)
    assert ma.keys() == mb.keys()
    for k in ma:
        assert np.array_equal(ma[k], mb[k]), k
    for name in ("mesh.ply", "hull.npz"):
        assert np.array_equal(load_scene_mesh(a, name[:4]).vertices, load_scene_mesh(b, name[:4]).vertices), name
    ja, jb = load_scene_meta(a), load_scene_meta(b)
    for key in ("seeds", "cameras", "envmap", "shape", "hull"):
        assert ja[key] == jb[key], key


@pytest.fixture(scope="module")
def made(tmp_path_factory, shared_envmaps):
    root = tmp_path_factory.mktemp("dataset") / "a"
    summary = generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED, config=TINY, workers=1)
    assert summary["made"] == list(range(SCENES)) and summary["skipped"] == 0
    return root


VARIED = dataclasses.replace(TINY, ior_range=(1.3, 1.7), ior_per_shape=2)


@pytest.fixture(scope="module")
def varied(tmp_path_factory, shared_envmaps):
    """Scenes 0 and 1 of a split with two IoRs in [1.3, 1.7] per shape, `made`'s seed and split."""
    root = tmp_path_factory.mktemp("dataset") / "varied"
    summary = generate_dataset(root, 2, views=VIEWS, split="train", seed=SEED, config=VARIED, workers=1)
    assert summary["made"] == [0, 1]
    return root


def test_generate_writes_compact_scene_files(made):
    cfg = json.loads((made / "train" / "config.json").read_text())
    assert cfg["views"] == VIEWS and cfg["seed"] == SEED and cfg["config"]["width"] == 64
    for i in range(SCENES):
        d = scene(made, i)
        assert sorted(p.name for p in d.iterdir()) == sorted(SCENE_FILES)
        # every member loads without unpickling, with the documented dtypes and shapes
        with zipfile.ZipFile(d / "maps.npz") as z:
            assert all(info.compress_type == zipfile.ZIP_DEFLATED for info in z.infolist())
        with np.load(d / "maps.npz", allow_pickle=False) as z:
            maps = {k: z[k] for k in z.files}
        assert set(maps) == set(MAP_KEYS)
        for k in ("image", "n1", "n2", "vh_n1", "vh_n2"):
            assert maps[k].dtype == np.float16 and maps[k].shape == (VIEWS, 48, 64, 3), k
        for k in ("mask", "valid", "tir", "vh_mask", "vh_valid", "vh_tir"):
            assert maps[k].dtype == bool and maps[k].shape == (VIEWS, 48, 64), k
        assert np.isfinite(maps["image"].astype(np.float32)).all() and maps["image"].min() >= 0
        # normals are unit where defined, zero elsewhere; N1 faces the camera
        n1 = maps["n1"].astype(np.float32)
        assert np.array_equal(np.abs(n1).sum(-1) > 0, maps["mask"])
        assert np.allclose(np.linalg.norm(n1[maps["mask"]], axis=-1), 1, atol=2e-3)
        assert (n1[maps["mask"]][:, 2] > -0.05).all()
        assert not (maps["valid"] & maps["tir"]).any() and not (maps["valid"] & ~maps["mask"]).any()
        assert maps["valid"].sum() > 0.2 * maps["mask"].sum()
        vh1 = maps["vh_n1"].astype(np.float32)
        assert np.array_equal(np.abs(vh1).sum(-1) > 0, maps["vh_mask"])
        # the hull's silhouettes are the masks up to a pixel along the rims
        assert (maps["vh_mask"] != maps["mask"]).mean() < 0.02
        meta = load_scene_meta(d)
        assert meta["index"] == i and meta["views"] == VIEWS and len(meta["cameras"]["origin"]) == VIEWS
        assert meta["envmap"]["source"] in ("natural", "procedural")
        assert set(meta["timings"]) >= {"shape", "envmap", "render", "hull", "hull_two_bounce", "write"}
        gt = load_scene_mesh(d, "mesh")
        assert gt.is_watertight and np.linalg.norm(gt.vertices, axis=1).max() == pytest.approx(1, abs=1e-5)


def test_resume_skips_finished_and_redoes_unfinished(made, tmp_path):
    root = tmp_path / "c"
    shutil.copytree(made, root)
    (scene(root, 1) / "meta.json").unlink()  # interrupted before the finished marker
    (scene(root, 1) / "maps.npz").write_bytes(b"half")
    stamp = (scene(root, 0) / "maps.npz").stat().st_mtime_ns
    summary = generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED, config=TINY, workers=1)
    assert summary["made"] == [1] and summary["skipped"] == SCENES - 1
    assert (scene(root, 0) / "maps.npz").stat().st_mtime_ns == stamp
    assert_same_scene(scene(root, 1), scene(made, 1))
    # settings that would mix two kinds of scenes in one folder are refused
    with pytest.raises(LookingGlassError, match="views"):
        generate_dataset(root, SCENES, views=10, split="train", seed=SEED, config=TINY)
    with pytest.raises(LookingGlassError, match="seed"):
        generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED + 1, config=TINY)
    with pytest.raises(LookingGlassError, match="width"):
        generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED,
                         config=dataclasses.replace(TINY, width=80))


def test_shards_and_workers_reproduce_the_full_run(made, tmp_path):
    root = tmp_path / "b"
    s1 = generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED, config=TINY, workers=2, shard=(1, 2))
    s2 = generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED, config=TINY, workers=1, shard=(2, 2))
    assert s1["made"] == [0, 2] and s2["made"] == [1, 3] and s1["workers"] == 2
    for i in range(SCENES):
        assert_same_scene(scene(root, i), scene(made, i))


def test_splits_use_disjoint_seeds_and_envmaps(shared_envmaps):
    train = {tuple(scene_seeds(0, "train", i).values()) for i in range(50)}
    test = {tuple(scene_seeds(0, "test", i).values()) for i in range(50)}
    assert not train & test and len(train) == 50
    from lookingglass.data.dataset import split_envmap_names

    tr, te = split_envmap_names(TINY, "train"), split_envmap_names(TINY, "test")
    assert sorted(te) == sorted(TINY.test_envmaps) and not set(tr) & set(te)
    assert len(tr) + len(te) == len(shared_envmaps)


def _camera_rays(meta, pixels):
    """DESIGN.md's pinhole model written out in numpy (independent of physics.camera)."""
    c = meta["cameras"]
    W, H = meta["width"], meta["height"]
    out_o, out_d, frames = [], [], []
    for v, row, col in pixels:
        o, t, up = (np.asarray(c[k][v], dtype=np.float64) for k in ("origin", "target", "up"))
        f = (t - o) / np.linalg.norm(t - o)
        r = np.cross(f, up)
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        tx = np.tan(np.radians(c["fov_x_deg"][v]) / 2)
        x, y = 2 * (col + 0.5) / W - 1, 1 - 2 * (row + 0.5) / H
        d = f + x * tx * r + y * tx * (H / W) * u
        out_o.append(o)
        out_d.append(d / np.linalg.norm(d))
        frames.append(np.stack([r, u, -f]))
    return np.array(out_o), np.array(out_d), np.array(frames)


def _smooth_hit(mesh, origins, dirs):
    """First hits by trimesh's pure-numpy intersector: points, smooth normals, hit flags."""
    loc, ray, tri = RayMeshIntersector(mesh).intersects_location(origins, dirs, multiple_hits=False)
    hit = np.zeros(len(origins), bool)
    hit[ray] = True
    points, normals = np.zeros_like(origins), np.zeros_like(origins)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], loc)
    n = (mesh.vertex_normals[mesh.faces[tri]] * bary[:, :, None]).sum(1)
    points[ray], normals[ray] = loc, n / np.linalg.norm(n, axis=1, keepdims=True)
    return hit, points, normals


def _angle_deg(a, b):
    cos = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


@pytest.mark.parametrize("split_name, index", [("made", 0), ("varied", 1)])
def test_gt_normals_match_an_independent_ray_cast(split_name, index, request):
    """Also for a drawn IoR: the second hits follow Snell's law with meta.json's IoR."""
    from scipy import ndimage

    d = scene(request.getfixturevalue(split_name), index)
    maps, meta, mesh = load_maps(d), load_scene_meta(d), load_scene_mesh(d, "mesh")
    rng = np.random.default_rng(0)
    interior = np.stack([ndimage.binary_erosion(m, iterations=2) for m in maps["mask"]])
    outside = np.stack([~ndimage.binary_dilation(m, iterations=2) for m in maps["mask"]])
    pick = lambda m, n: np.argwhere(m)[rng.choice(int(m.sum()), n, replace=False)]  # noqa: E731
    pixels = np.concatenate([pick(interior, 40), pick(outside, 10)])
    o, dirs, frames = _camera_rays(meta, pixels)
    hit, p1, n1 = _smooth_hit(mesh, o, dirs)
    assert hit[:40].all() and not hit[40:].any()
    stored_n1 = maps["n1"][tuple(pixels[:40].T)].astype(np.float64)
    n1_cam = np.einsum("kij,kj->ki", frames[:40], n1[:40])
    assert _angle_deg(stored_n1, n1_cam).max() < 0.1  # float16 storage: ~0.02 deg

    # second hit: refract by Snell's law (written out here), cast again from inside
    valid = maps["valid"][tuple(pixels[:40].T)]
    assert valid.sum() >= 10
    dd, nn = dirs[:40][valid], n1[:40][valid]
    eta = meta["ext_ior"] / meta["ior"]
    cos_i = -(dd * nn).sum(1, keepdims=True)
    t = eta * dd + (eta * cos_i - np.sqrt(1 - eta ** 2 * (1 - cos_i ** 2))) * nn
    hit2, _, n2 = _smooth_hit(mesh, p1[:40][valid] + 1e-4 * t, t)
    assert hit2.all()
    stored_n2 = maps["n2"][tuple(pixels[:40][valid].T)].astype(np.float64)
    n2_cam = np.einsum("kij,kj->ki", frames[:40][valid], n2)
    err = _angle_deg(stored_n2, n2_cam)
    # (a ray grazing a triangle edge may pick the neighbour in float32 Embree vs float64 here)
    assert np.median(err) < 0.05 and (err < 0.1).mean() >= 0.9, err


def test_ior_per_shape_gives_each_shape_its_own_iors(made, varied):
    """ior_per_shape 2, ior_range [1.3, 1.7]: scenes 0 and 1 show scene 0's shape, rig and map
    (that of the default split with the same seed) with two IoRs drawn in the range, the renderer
    and the hull's tracing at that IoR; the default split's scene keeps the glass's 1.4723."""
    base = load_scene_meta(scene(made, 0))
    assert base["ior"] == 1.4723 and "shape_index" not in base
    metas = [load_scene_meta(scene(varied, i)) for i in (0, 1)]
    iors = [m["ior"] for m in metas]
    assert all(1.3 <= x <= 1.7 for x in iors) and abs(iors[0] - iors[1]) > 1e-3, iors
    assert iors == [1.5812, 1.6302]  # each scene's own stream: the same on every run
    gt = load_scene_mesh(scene(made, 0), "mesh").vertices
    maps0 = load_maps(scene(made, 0))
    for i, meta in enumerate(metas):
        assert meta["index"] == i and meta["shape_index"] == 0
        assert all(meta[key] == base[key] for key in ("seeds", "cameras", "envmap", "shape"))
        assert np.array_equal(load_scene_mesh(scene(varied, i), "mesh").vertices, gt)
        assert np.array_equal(load_scene_mesh(scene(varied, i), "hull").vertices,
                              load_scene_mesh(scene(made, 0), "hull").vertices)
        maps = load_maps(scene(varied, i))
        for key in ("mask", "n1", "vh_mask", "vh_n1"):  # the first hits do not see the IoR
            assert np.array_equal(maps[key], maps0[key]), key
        for key in ("image", "n2", "vh_n2"):  # the refracted paths do
            assert not np.array_equal(maps[key], maps0[key]), key
    # the dataset serves each scene's own IoR, or one an evaluation holds
    ds = TransparentSceneDataset(varied, "train")
    assert [ds.capture(i).ior for i in (0, 1)] == iors
    held = ds.capture(1, 1.4723)
    assert held.ior == 1.4723 and held.spec.ior == iors[1]
    with pytest.raises(LookingGlassError, match="from 1.0 to 3.0"):
        ds.capture(0, 0.9)
    cfg = json.loads((varied / "train" / "config.json").read_text())["config"]
    assert cfg["ior_range"] == [1.3, 1.7] and cfg["ior_per_shape"] == 2 and "ior" not in cfg


def test_normal_evaluation_holds_the_ior(varied):
    """eval-normals --ior 1.4723 on scene 0 (IoR 1.5812): the hull's inputs and the rendering layer
    take 1.4723, the ground truth stays the scene's own, so even the true normals render worse;
    eval-shapes' stages get the capture at 1.4723 too."""
    from lookingglass.normals.evaluate import _NormalEvaluation

    ds = TransparentSceneDataset(varied, "train")
    own = _NormalEvaluation(ds, {}, None).scene(0)
    held = _NormalEvaluation(ds, {}, None, ior=1.4723).scene(0)
    own, held = ({k: v.summary() for k, v in rows.items()} for _, rows in (own, held))
    assert own["gt"]["n1_mean"] == held["gt"]["n1_mean"] < 1e-3 and own["gt"]["n2_mean"] < 1e-3  # the same truth
    assert held["gt"]["render_error"] > own["gt"]["render_error"]  # 0.1094 against 0.1079 here
    # the hull's first hits do not see the IoR; its second hits, traced at 1.4723, are further from
    # the truth's (25.8 -> 26.1 degrees mean here)
    assert held["vh"]["n1_mean"] == own["vh"]["n1_mean"]
    assert held["vh"]["n2_mean"] > own["vh"]["n2_mean"] + 0.1

    # eval-shapes hands its stages the same held capture (stopped once it has it)
    from lookingglass.points.evaluate import _ShapeEvaluation
    from lookingglass.points.stage import SurfaceConfig

    class Stop(Exception):
        pass

    seen = []

    def capture(i, ior=None):
        seen.append(TransparentSceneDataset.capture(ds, i, ior).ior)
        raise Stop

    ds.capture = capture
    for ior in (1.4723, None):
        with pytest.raises(Stop):
            _ShapeEvaluation(ds, None, None, ("RE",), None, SurfaceConfig(), ior=ior).scene(0)
    assert seen == [1.4723, 1.5812]


def test_split_written_before_the_ior_range_still_resumes(made, tmp_path):
    """A config.json with the single "ior" and without the keys added since reads as the default
    config: the folder resumes (nothing redone) and loads; other IoR settings are refused."""
    root = tmp_path / "old"
    shutil.copytree(made, root)
    path = root / "train" / "config.json"
    saved = json.loads(path.read_text())
    cfg = saved["config"]
    for key in ("ior_range", "ior_per_shape", "family_weights", "hull_mask_scale"):
        cfg.pop(key)
    cfg["ior"] = 1.4723
    path.write_text(json.dumps(saved))
    summary = generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED, config=TINY, workers=1)
    assert summary["made"] == [] and summary["skipped"] == SCENES
    assert TransparentSceneDataset(root, "train").config == TINY
    with pytest.raises(LookingGlassError, match="ior_per_shape, config.ior_range"):
        generate_dataset(root, SCENES, views=VIEWS, split="train", seed=SEED, config=VARIED)


@pytest.mark.parametrize("bad, said", [
    ({"ior_range": (1.7, 1.3)}, "ior_range: LO must be at most HI, got 1.7 1.3"),
    ({"ior_range": (0.5, 1.3)}, "ior_range must be an index of refraction from 1.0 to 3.0"),
    ({"ior_range": (1.3, 3.5)}, "got 3.5"),
    ({"ior_per_shape": 0}, "ior_per_shape must be at least 1"),
])
def test_bad_ior_settings_are_refused(bad, said):
    with pytest.raises(LookingGlassError) as info:
        DatasetConfig(**bad)
    assert said in str(info.value)


def test_visual_hull_contains_the_object(made):
    # The hull touches the object along the silhouette rims, so surface points lie on both sides
    # of it there, by up to half a pixel footprint (0.029 at 64 x 48 and distance 3): pixel-centre
    # masks decide each rim pixel one way or the other.
    pixel = 2 * 3 * np.tan(np.radians(63.4 / 2)) / 64
    for i in range(SCENES):
        gt, hull = load_scene_mesh(scene(made, i), "mesh"), load_scene_mesh(scene(made, i), "hull")
        assert hull.is_watertight and hull.volume > gt.volume
        pts, face = trimesh.sample.sample_surface(gt, 2000, seed=i)
        inside = hull.contains(pts)
        if (~inside).any():
            _, dist, _ = trimesh.proximity.closest_point(hull, pts[~inside])
            assert dist.max() < 0.7 * pixel, dist.max() / pixel
        # half a pixel below the surface, the object is inside the hull
        assert hull.contains(pts - 0.5 * pixel * gt.face_normals[face]).mean() >= 0.99


def test_dataset_normalization_and_envmap_factor(made):
    ds = TransparentSceneDataset(made, "train")
    assert len(ds) == SCENES
    item = ds[2]
    raw = load_maps(scene(made, 2))["image"].astype(np.float64)  # (V, H, W, 3)
    factor = float(item["factor"])
    assert (raw * factor).mean() == pytest.approx(0.5, rel=1e-5)  # before clipping
    expected = np.clip(raw * factor, 0, 1).transpose(0, 3, 1, 2)
    assert np.allclose(item["image"].numpy(), expected, atol=1e-6)
    assert item["image"].max() <= 1 and item["image"].min() >= 0
    meta = ds.meta(2)
    env = envmap_from_description(meta["envmap"], None, meta["envmap_height"])
    served = item["envmap"].permute(1, 2, 0).numpy()
    assert served.shape == env.shape == (32, 64, 3)
    pos = env > 1e-6
    assert np.allclose(served[pos] / env[pos], factor, rtol=1e-5)
    assert served.max() > 1 or env.max() * factor <= 1  # E is not clipped
    # tensors in (V, C, H, W) / (V, H, W), cameras as stored
    assert item["n1"].shape == (VIEWS, 3, 48, 64) and item["mask"].dtype == torch.bool
    assert torch.equal(item["mask"], torch.from_numpy(load_maps(scene(made, 2))["mask"]))
    assert np.allclose(item["origin"].numpy(), np.asarray(meta["cameras"]["origin"]), atol=1e-6)

    # augmentation: the target mean is drawn from U[0.4, 0.6], reproducibly for a seed
    a = TransparentSceneDataset(made, "train", augment=True, seed=5)
    b = TransparentSceneDataset(made, "train", augment=True, seed=5)
    draws = [float(a[1]["target_mean"]) for _ in range(4)]
    assert draws == [float(b[1]["target_mean"]) for _ in range(4)]
    assert len(set(draws)) == 4 and all(0.4 <= m <= 0.6 for m in draws)
    again = a[1]
    raw1 = load_maps(scene(made, 1))["image"].astype(np.float64)
    assert (raw1 * float(again["factor"])).mean() == pytest.approx(float(again["target_mean"]), rel=1e-5)


def test_dataset_view_subsets_and_errors(made, tmp_path):
    assert rig_subset(10, 5) == [0, 6, 2, 8, 4] and rig_subset(20, 10) == list(range(0, 20, 2))
    with pytest.raises(LookingGlassError):
        TransparentSceneDataset(made, "train", views=10)  # more than stored
    with pytest.raises(LookingGlassError, match="config.json"):
        TransparentSceneDataset(tmp_path, "train")
    with pytest.raises(LookingGlassError):
        TransparentSceneDataset(made, "validation")


def test_parse_shard():
    assert parse_shard("1/1") == (1, 1) and parse_shard(" 3 / 8 ") == (3, 8)
    for bad in ("0/2", "3/2", "2", "a/b", "1/0", "-1/2", "1/2/3"):
        with pytest.raises(LookingGlassError, match="shard"):
            parse_shard(bad)
    with pytest.raises(LookingGlassError, match="views"):
        generate_dataset("unused", 2, views=7)


CLI = [sys.executable, "-m", "lookingglass.cli", "generate"]


def test_cli_generate_and_bad_shard(tmp_path, shared_envmaps):
    proc = subprocess.run([*CLI, "--out", tmp_path / "d", "--scenes", "1", "--views", "5", "--split", "test",
                           "--workers", "1", "--seed", "2", "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    meta = load_scene_meta(tmp_path / "d" / "test" / "scene_00000")
    assert meta["split"] == "test" and meta["width"] == 128 and meta["height"] == 96
    if meta["envmap"]["source"] == "natural":
        assert meta["envmap"]["name"] in DatasetConfig().test_envmaps
    proc = subprocess.run([*CLI, "--out", tmp_path / "e", "--scenes", "4", "--shard", "5/4"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--shard" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "e").exists()
