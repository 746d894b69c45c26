"""Scene folder I/O: typed scene.json, load_capture's checks, save_scene round trips."""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from lookingglass.capture.images import linear_to_srgb, read_envmap, write_image
from lookingglass.capture.scene import (Capture, SceneSpec, ViewSpec, check_object_in_front, load_capture,
                                        save_scene, triangulate_mask_centroids)
from lookingglass.errors import LookingGlassError, LookingGlassWarning
from lookingglass.physics.camera import Cameras

SPHERE_CENTER = np.array([0.3, 0.1, -0.2])
SPHERE_RADIUS = 0.5


# ---- synthetic captures (also used by test_paper_import.py) ---------------------------------
def rig(V: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Look-at parameters of V cameras around the origin: origin, target, up each (V, 3)."""
    rng = np.random.default_rng(seed)
    az = np.linspace(0, 2 * np.pi, V, endpoint=False) + rng.uniform(-0.2, 0.2, V)
    polar = np.radians(np.where(np.arange(V) % 2 == 0, 60.0, 105.0) + rng.uniform(-8, 8, V))
    dist = 2.6 + 0.8 * rng.random(V)
    origin = dist[:, None] * np.stack([np.sin(polar) * np.cos(az), np.cos(polar), np.sin(polar) * np.sin(az)], 1)
    target = rng.uniform(-0.05, 0.05, (V, 3))
    up = np.array([0.0, 1.0, 0.0]) + rng.uniform(-0.1, 0.1, (V, 3))
    return origin, target, up


def sphere_masks(cams: Cameras, center=SPHERE_CENTER, radius=SPHERE_RADIUS) -> np.ndarray:
    """(V, H, W) bool: pixels whose ray passes within `radius` of `center` (in front of the camera)."""
    o, d = cams.to(dtype=torch.float64).pixel_rays()
    rel = torch.as_tensor(center, dtype=torch.float64) - o
    t = (rel * d).sum(-1)
    dist2 = (rel * rel).sum(-1) - t * t
    return ((t > 0) & (dist2 < radius**2)).numpy()


def synthetic_images(masks: np.ndarray, seed: int = 0) -> np.ndarray:
    """(V, H, W, 3) float32 linear in [0, 1]: a per-view gradient with the object tinted."""
    V, H, W = masks.shape
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.linspace(0, 1, H), np.linspace(0, 1, W), indexing="ij")
    base = np.stack([xx, yy, 0.5 * (xx + yy)], -1)[None] * rng.uniform(0.3, 0.9, (V, 1, 1, 3))
    tint = np.where(masks[..., None], np.array([0.2, 0.6, 0.9]), 1.0)
    return (base * tint).astype(np.float32)


def synthetic_envmap(h: int = 16, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.05, 2.0, (h, 2 * h, 3)).astype(np.float32)


def make_scene(folder: Path, V: int = 6, W: int = 64, H: int = 48, image_ext: str = ".png",
               env_name: str = "envmap.hdr", envmap_scale: float = 1.0, seed: int = 0):
    """Write a valid synthetic scene folder; returns (spec, images, masks, envmap)."""
    origin, target, up = rig(V, seed)
    cams = Cameras.look_at(origin, target, up, 63.4, W, H, dtype=torch.float64)
    masks = sphere_masks(cams)
    images = synthetic_images(masks, seed)
    envmap = synthetic_envmap(seed=seed)
    views = [ViewSpec(image=f"images/{i:02d}{image_ext}", mask=f"masks/{i:02d}.png", origin=tuple(origin[i]),
                      target=tuple(target[i]), up=tuple(up[i]), fov_x_deg=63.4) for i in range(V)]
    spec = SceneSpec(envmap=env_name, envmap_scale=envmap_scale, views=views)
    save_scene(folder, spec, images, masks, envmap)
    return spec, images, masks, envmap


def edit_json(folder: Path, fn) -> None:
    path = folder / "scene.json"
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data, indent=2))


def tree_digest(folder: Path) -> dict[str, tuple[str, int]]:
    return {str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def scene(tmp_path: Path):
    folder = tmp_path / "scene"
    return (folder, *make_scene(folder))


def load_quiet(folder) -> Capture:
    with warnings.catch_warnings():
        warnings.simplefilter("error", LookingGlassWarning)  # a valid synthetic scene has nothing odd
        return load_capture(folder)


def expect_error(folder, *fragments) -> str:
    with pytest.raises(LookingGlassError) as info:
        load_capture(folder)
    message = str(info.value)
    for frag in fragments:
        assert frag in message, f"{frag!r} not in {message!r}"
    return message


# ---- round trips -----------------------------------------------------------------------------
def test_round_trip_exr_is_exact(tmp_path):
    folder = tmp_path / "s"
    spec, images, masks, envmap = make_scene(folder, image_ext=".exr", env_name="sky.exr", envmap_scale=2.0)
    cap = load_quiet(folder)
    assert cap.spec == spec
    assert cap.images.dtype == np.float32 and cap.images.shape == (6, 48, 64, 3)
    assert cap.masks.dtype == bool and cap.masks.shape == (6, 48, 64)
    np.testing.assert_array_equal(cap.images, images)
    np.testing.assert_array_equal(cap.masks, masks)
    np.testing.assert_array_equal(cap.envmap, envmap)  # file holds envmap / 2, load multiplies by 2
    np.testing.assert_allclose(read_envmap(folder / "sky.exr"), envmap / 2)
    assert (cap.num_views, cap.width, cap.height, cap.ior) == (6, 64, 48, 1.4723)
    assert cap.image_paths == [folder / f"images/{i:02d}.exr" for i in range(6)]
    assert cap.mask_paths == [folder / f"masks/{i:02d}.png" for i in range(6)]
    ref = spec.cameras(64, 48, dtype=torch.float32)
    assert cap.cameras.origin.dtype == torch.float32 and (cap.cameras.width, cap.cameras.height) == (64, 48)
    torch.testing.assert_close(cap.cameras.origin, ref.origin)
    torch.testing.assert_close(cap.cameras.basis, ref.basis)
    # and the whole capture saves back to an identical folder
    save_scene(tmp_path / "again", cap.spec, cap.images, cap.masks, cap.envmap)
    again = load_quiet(tmp_path / "again")
    np.testing.assert_array_equal(again.images, cap.images)
    np.testing.assert_array_equal(again.envmap, cap.envmap)


def test_round_trip_png_within_8bit(scene):
    folder, spec, images, masks, envmap = scene
    cap = load_quiet(folder)
    assert cap.spec == spec
    np.testing.assert_array_equal(cap.masks, masks)
    # 8-bit sRGB quantization: at most half a code value in sRGB space
    err = np.abs(linear_to_srgb(cap.images) - linear_to_srgb(images)).max()
    assert err <= 0.5 / 255 + 1e-5
    # RGBE: one shared exponent, so the error is relative to the pixel's brightest channel
    assert (np.abs(cap.envmap - envmap) <= envmap.max(-1, keepdims=True) / 100).all()


def test_linear_encoding_round_trip(tmp_path):
    folder = tmp_path / "s"
    origin, target, up = rig(4)
    cams = Cameras.look_at(origin, target, up, 50.0, 40, 30)
    masks = sphere_masks(cams)
    images = synthetic_images(masks)
    spec = SceneSpec(envmap="e.hdr", image_encoding="linear",
                     views=[ViewSpec(f"i{i}.png", f"m{i}.png", tuple(origin[i]), tuple(target[i]), tuple(up[i]), 50.0)
                            for i in range(4)])
    save_scene(folder, spec, images, masks, synthetic_envmap())
    raw = cv2.imread(str(folder / "i0.png"))[..., ::-1]
    np.testing.assert_array_equal(raw, np.round(images[0] * 255).astype(np.uint8))  # not sRGB-encoded
    cap = load_quiet(folder)
    assert np.abs(cap.images - images).max() <= 0.5 / 255 + 1e-6


def test_spec_dict_round_trip(scene):
    _, spec, *_ = scene
    data = spec.to_json_dict()
    assert list(data) == ["ior", "envmap", "envmap_scale", "image_encoding", "views"]
    again, notes = SceneSpec.from_dict(json.loads(json.dumps(data)))
    assert again == spec and notes == []


def test_optional_keys_default(scene):
    folder, spec, *_ = scene
    edit_json(folder, lambda d: [d.pop(k) for k in ("ior", "envmap_scale", "image_encoding")])
    got, notes = SceneSpec.from_json(folder / "scene.json")
    assert (got.ior, got.envmap_scale, got.image_encoding) == (1.4723, 1.0, "srgb") and notes == []


def test_inputs_unchanged(scene):
    folder, *_ = scene
    before = tree_digest(folder)
    load_quiet(folder)
    SceneSpec.from_json(folder / "scene.json")
    assert tree_digest(folder) == before


def test_load_twenty_views_is_fast(tmp_path):
    folder = tmp_path / "big"
    make_scene(folder, V=20, W=480, H=360)
    start = time.perf_counter()
    cap = load_quiet(folder)
    elapsed = time.perf_counter() - start
    assert cap.images.shape == (20, 360, 480, 3)
    assert elapsed < 2.0, f"loading 20 views of 480x360 took {elapsed:.2f} s"


# ---- save_scene ------------------------------------------------------------------------------
def test_save_refuses_existing_files_unless_overwrite(scene):
    folder, spec, images, masks, envmap = scene
    with pytest.raises(LookingGlassError, match="already exists"):
        save_scene(folder, spec)
    before = (folder / "images/00.png").read_bytes()
    save_scene(folder, spec, images * 0.5, overwrite=True)
    assert (folder / "images/00.png").read_bytes() != before
    assert not list(folder.rglob("*.part*")), "temporary files left behind"


def test_save_checks_array_shapes(tmp_path, scene):
    _, spec, images, masks, envmap = scene
    with pytest.raises(LookingGlassError, match="images must be"):
        save_scene(tmp_path / "a", spec, images[:3])
    with pytest.raises(LookingGlassError, match="masks are"):
        save_scene(tmp_path / "b", spec, images, masks[:, :10])
    with pytest.raises(LookingGlassError, match="envmap must be"):
        save_scene(tmp_path / "c", spec, envmap=envmap[:, :10])
    bad = images.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(LookingGlassError, match="NaN"):
        save_scene(tmp_path / "d", spec, bad)
    assert not (tmp_path / "d" / "scene.json").exists()


def test_save_rejects_invalid_spec(tmp_path, scene):
    _, spec, *_ = scene
    spec.views[1].fov_x_deg = 200.0
    with pytest.raises(LookingGlassError, match=r"views\[1\].fov_x_deg"):
        save_scene(tmp_path / "x", spec)


# ---- scene.json errors -----------------------------------------------------------------------
def test_missing_folder_and_scene_file(tmp_path):
    expect_error(tmp_path / "nope", "nope", "scene folder not found")
    (tmp_path / "empty").mkdir()
    expect_error(tmp_path / "empty", "empty", "no scene.json")


def test_malformed_json_names_line(scene):
    folder, *_ = scene
    text = (folder / "scene.json").read_text().splitlines()
    text[2] = text[2].rstrip(",")  # drop a comma on line 3
    (folder / "scene.json").write_text("\n".join(text))
    expect_error(folder, "scene.json", "invalid JSON at line 4")


@pytest.mark.parametrize("edit, fragments", [
    (lambda d: d["views"][2].__setitem__("origin", [1, 2]), ["views[2].origin", "3 finite numbers"]),
    (lambda d: d["views"][0].__setitem__("up", ["a", 0, 1]), ["views[0].up"]),
    (lambda d: d["views"][1].__setitem__("fov_x_deg", 180), ["views[1].fov_x_deg", "(0, 180)"]),
    (lambda d: d["views"][1].__setitem__("fov_x_deg", "60"), ["views[1].fov_x_deg must be a number"]),
    (lambda d: d["views"][1].__setitem__("fov_x_deg", True), ["views[1].fov_x_deg must be a number"]),
    (lambda d: d.__setitem__("ior", 0), ["ior must be an index of refraction from 1.0 to 3.0", "got 0"]),
    (lambda d: d.__setitem__("ior", -1.5), ["ior must be an index of refraction from 1.0 to 3.0", "got -1.5"]),
    (lambda d: d.__setitem__("ior", "1.5"), ["ior must be a number"]),
    (lambda d: d.__setitem__("envmap_scale", 0), ["envmap_scale must be > 0"]),
    (lambda d: d.__setitem__("image_encoding", "gamma"), ["image_encoding"]),
    (lambda d: d.__setitem__("views", []), ["'views' is empty"]),
    (lambda d: d.__setitem__("views", {"a": 1}), ["'views' must be a list"]),
    (lambda d: d.pop("envmap"), ["missing required key 'envmap'"]),
    (lambda d: d["views"][3].__setitem__("fov", d["views"][3].pop("fov_x_deg")),
     ["views[3] is missing required key 'fov_x_deg'", "'fov'"]),
    (lambda d: d["views"][4].__setitem__("image", 7), ["views[4].image"]),
    (lambda d: d["views"][2].__setitem__("target", d["views"][2]["origin"]), ["views[2]", "origin equals target"]),
    (lambda d: d["views"][2].__setitem__("up", (np.array(d["views"][2]["target"]) - d["views"][2]["origin"]).tolist()),
     ["views[2]", "images/02.png", "parallel to the viewing direction"]),
    (lambda d: d["views"][2].__setitem__("up", [0, 0, 0]), ["views[2]", "zero vector"]),
])
def test_invalid_fields(scene, edit, fragments):
    folder, *_ = scene
    edit_json(folder, edit)
    expect_error(folder, "scene.json", *fragments)


def test_top_level_not_object(scene):
    folder, *_ = scene
    (folder / "scene.json").write_text("[1, 2]")
    expect_error(folder, "scene.json", "top level must be a JSON object")


def test_nan_literal_rejected(scene):
    folder, *_ = scene
    text = (folder / "scene.json").read_text().replace('"ior": 1.4723', '"ior": NaN')
    (folder / "scene.json").write_text(text)
    expect_error(folder, "ior must be finite")


# ---- file errors -----------------------------------------------------------------------------
@pytest.mark.parametrize("victim", ["images/03.png", "masks/01.png", "envmap.hdr"])
def test_missing_file_named(scene, victim):
    folder, *_ = scene
    (folder / victim).unlink()
    expect_error(folder, victim, "file not found")


def test_all_missing_files_listed(scene):
    folder, *_ = scene
    (folder / "images/01.png").unlink()
    (folder / "masks/04.png").unlink()
    expect_error(folder, "images/01.png", "also missing", "masks/04.png")


def test_unreadable_image_named(scene):
    folder, *_ = scene
    (folder / "images/02.png").write_bytes(b"this is not a png")
    expect_error(folder, "images/02.png", "cannot read image")


def test_image_size_differs_between_views(scene):
    folder, spec, images, *_ = scene
    write_image(folder / "images/04.png", np.zeros((40, 64, 3), np.float32))
    expect_error(folder, "images/04.png", "64x40", "64x48", "one image size")


def test_mask_size_mismatch(scene):
    folder, *_ = scene
    cv2.imwrite(str(folder / "masks/02.png"), np.full((48, 60), 255, np.uint8))
    expect_error(folder, "masks/02.png", "60x48", "images/02.png is 64x48")


def test_empty_mask(scene):
    folder, *_ = scene
    cv2.imwrite(str(folder / "masks/05.png"), np.zeros((48, 64), np.uint8))
    expect_error(folder, "masks/05.png", "empty")


def test_nan_in_envmap_named(tmp_path):
    folder = tmp_path / "s"
    make_scene(folder, env_name="sky.exr")
    env = synthetic_envmap()
    env[3, 5, 1] = np.nan
    write_image(folder / "sky.exr", env)
    expect_error(folder, "sky.exr", "NaN")


def test_inf_in_image_named(tmp_path):
    folder = tmp_path / "s"
    _, images, *_ = make_scene(folder, image_ext=".exr")
    img = images[1].copy()
    img[0, 0] = np.inf
    write_image(folder / "images/01.exr", img)
    expect_error(folder, "images/01.exr", "NaN or infinite")


# ---- cameras vs object -----------------------------------------------------------------------
def test_camera_looking_away(scene):
    folder, *_ = scene

    def turn_around(d):
        v = d["views"][3]
        v["target"] = [2 * o - t for o, t in zip(v["origin"], v["target"])]
    edit_json(folder, turn_around)
    message = expect_error(folder, "scene.json", "views[3] (images/03.png)", "behind this camera")
    assert "images/00.png" not in message and "views[2]" not in message


def test_camera_looking_sideways(scene):
    folder, *_ = scene

    def look_sideways(d):
        v = d["views"][1]
        o = np.array(v["origin"])
        side = np.cross(-o, [0.0, 1.0, 0.0])
        v["target"] = (o + side / np.linalg.norm(side)).tolist()
    edit_json(folder, look_sideways)
    message = expect_error(folder, "views[1] (images/01.png)", "outside")
    assert "views[0]" not in message and "views[4]" not in message


def test_triangulated_centre_matches_object(scene):
    folder, *_ = scene
    cap = load_quiet(folder)
    point, cond = triangulate_mask_centroids(cap.cameras, cap.masks)
    assert cond > 0.1
    assert np.linalg.norm(point - SPHERE_CENTER) < 0.05  # silhouette centroids ~ projected centre
    assert check_object_in_front(cap.cameras, cap.masks, [v.image for v in cap.spec.views]) is not None


def test_single_view_skips_object_check(tmp_path):
    folder = tmp_path / "one"
    make_scene(folder, V=1)
    assert load_quiet(folder).num_views == 1


# ---- warnings --------------------------------------------------------------------------------
def test_unknown_keys_warn_and_name_them(scene):
    folder, *_ = scene
    edit_json(folder, lambda d: (d.__setitem__("foo", 1), d["views"][3].__setitem__("fovx", 60)))
    with pytest.warns(LookingGlassWarning) as record:
        cap = load_capture(folder)
    messages = [str(w.message) for w in record]
    assert any("unknown key 'foo'" in m and "scene.json" in m and "ignored" in m for m in messages)
    assert any("unknown key 'fovx' in views[3]" in m and "did you mean 'fov_x_deg'" in m for m in messages)
    assert len(cap.warnings) == 2


def test_duplicate_cameras_warn(scene):
    folder, *_ = scene
    edit_json(folder, lambda d: d["views"][4].update({k: d["views"][1][k] for k in ("origin", "target", "up")}))
    pattern = r"views\[1\] \(images/01.png\) and views\[4\] \(images/04.png\) have identical cameras"
    with pytest.warns(LookingGlassWarning, match=pattern):
        try:
            load_capture(folder)
        except LookingGlassError:
            pass  # the mask of view 4 no longer matches its camera; the warning comes from parsing


def test_duplicate_cameras_warn_from_spec():
    v = ViewSpec("a.png", "m.png", (0, 0, 3), (0, 0, 0), (0, 1, 0), 60.0)
    w = ViewSpec("b.png", "n.png", (0, 0, 3), (0, 0, -1), (0, 2, 0), 60.0)  # same camera, other parameters
    _, notes = SceneSpec.from_dict(SceneSpec(envmap="e.hdr", views=[v, w]).to_json_dict())
    assert len(notes) == 1 and "identical cameras" in notes[0]


@pytest.mark.parametrize("ior", [0.8, 3.5, 0.9999])
def test_ior_outside_1_to_3_is_refused(scene, ior):
    folder, *_ = scene
    edit_json(folder, lambda d: d.__setitem__("ior", ior))
    message = expect_error(folder, "scene.json", f"ior must be an index of refraction from 1.0 to 3.0 (glass is "
                                                 f"about 1.5), got {ior}")
    assert message.count("\n") == 0


@pytest.mark.parametrize("ior", [1.0, 3.0, 1.6])
def test_ior_at_the_bounds_loads_without_a_warning(scene, ior):
    folder, *_ = scene
    edit_json(folder, lambda d: d.__setitem__("ior", ior))
    with warnings.catch_warnings():
        warnings.simplefilter("error", LookingGlassWarning)
        cap = load_capture(folder)
    assert cap.ior == ior and cap.spec.ior == ior
    held = cap.with_ior(1.3)  # an IoR held over scene.json's: every stage reads `ior`, the spec stays the file's
    assert (held.ior, held.spec.ior, cap.ior) == (1.3, ior, ior) and held.images is cap.images
    with pytest.raises(LookingGlassError, match="got 3.2"):
        cap.with_ior(3.2)
