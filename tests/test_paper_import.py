"""Importing the paper's real-capture layout (cam*.txt, photo folder, mask folder, envmap)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from lookingglass.capture.images import linear_to_srgb, read_image, write_image
from lookingglass.capture.paper_import import import_paper, natural_key, read_paper_cameras
from lookingglass.capture.scene import load_capture
from lookingglass.errors import LookingGlassError, LookingGlassWarning
from lookingglass.physics.camera import Cameras
from test_scene import SPHERE_CENTER, rig, sphere_masks, synthetic_envmap, synthetic_images, tree_digest

V_MASKED, V_PHOTOS = 12, 14
W_IN, H_IN = 160, 120  # photos and masks; imported at half size
FOV = 60.0


def write_layout(root: Path) -> dict:
    """A paper-style capture: 14 JPEG photos named 1..14 (one as .JPG), RGBA masks for 1..12 whose
    RGB is noise (the mask is in alpha), a camera file listing the 12 masked views in natural order
    with blank lines, and an .hdr envmap."""
    origin, target, up = rig(V_PHOTOS, seed=3)
    cams = Cameras.look_at(origin, target, up, FOV, W_IN, H_IN, dtype=torch.float64)
    masks = sphere_masks(cams)
    photos = synthetic_images(masks, seed=3)
    rng = np.random.default_rng(0)
    (root / "photos").mkdir(parents=True)
    (root / "masks").mkdir()
    for i in range(V_PHOTOS):
        name = f"{i + 1}.JPG" if i == 6 else f"{i + 1}.jpg"
        bgr = np.round(linear_to_srgb(photos[i]) * 255).astype(np.uint8)[..., ::-1]
        cv2.imwrite(str(root / "photos" / name), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    for i in range(V_MASKED):
        rgba = rng.integers(0, 256, (H_IN, W_IN, 4), dtype=np.uint8)
        rgba[..., 3] = np.where(masks[i], 255, 0)
        cv2.imwrite(str(root / "masks" / f"{i + 1}.png"), rgba)
    lines = [str(V_MASKED), ""]
    for i in range(V_MASKED):  # natural order of the mask stems: 1, 2, ..., 12
        lines += [" ".join(repr(float(c)) for c in vec) for vec in (origin[i], target[i], up[i])] + [""]
    (root / "cam12.txt").write_text("\n".join(lines))
    write_image(root / "env.hdr", synthetic_envmap())
    return dict(origin=origin, target=target, up=up, masks=masks, cams=cams,
                args=dict(cams=root / "cam12.txt", images=root / "photos", masks=root / "masks",
                          envmap=root / "env.hdr"))


@pytest.fixture
def layout(tmp_path):
    return write_layout(tmp_path / "paper")


def run_import(layout, out, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error", LookingGlassWarning)
        return import_paper(**layout["args"], out=out, **{"fov_x_deg": FOV, **kw})


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_natural_sort():
    assert sorted(["10", "2", "1", "12", "9"], key=natural_key) == ["1", "2", "9", "10", "12"]
    assert sorted(["im_10", "im_2", "IM_3"], key=natural_key) == ["im_2", "IM_3", "im_10"]
    stamps = ["LRM_20191113_010933", "LRM_20191113_004003", "LRM_20191113_010451"]
    assert sorted(stamps, key=natural_key) == sorted(stamps)  # the release's names: same as plain sort


def test_import_resized(layout, tmp_path):
    out = tmp_path / "scene"
    assert run_import(layout, out, size=(W_IN // 2, H_IN // 2), envmap_scale=0.5) == out
    scene = json.loads((out / "scene.json").read_text())
    cap = load_capture(out)
    stems = [str(i + 1) for i in range(V_MASKED)]
    # matching: the 12 masked photos, natural order, extra photos 13 and 14 left out, "7.JPG" found
    assert [v["image"] for v in scene["views"]] == [f"images/{s}.png" for s in stems]
    assert [v["mask"] for v in scene["views"]] == [f"masks/{s}.png" for s in stems]
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(f"{s}.png" for s in stems)
    # camera lines, in order
    for i, v in enumerate(scene["views"]):
        assert v["origin"] == layout["origin"][i].tolist()
        assert v["target"] == layout["target"][i].tolist()
        assert v["up"] == layout["up"][i].tolist()
        assert v["fov_x_deg"] == FOV
    # envmap copied unchanged, scale recorded
    assert (out / "envmap.hdr").read_bytes() == layout["args"]["envmap"].read_bytes()
    assert scene["envmap_scale"] == 0.5
    # size, and masks read from the alpha channel and paired with the right cameras
    assert cap.images.shape == (V_MASKED, H_IN // 2, W_IN // 2, 3)
    assert cap.masks.shape == (V_MASKED, H_IN // 2, W_IN // 2)
    silhouettes = sphere_masks(cap.cameras)
    for i in range(V_MASKED):
        assert iou(cap.masks[i], silhouettes[i]) > 0.9, f"view {i + 1}"
    lexicographic = sorted(range(V_MASKED), key=lambda i: str(i + 1))  # 1, 10, 11, 12, 2, ...
    assert np.mean([iou(cap.masks[j], silhouettes[i]) for i, j in enumerate(lexicographic)]) < 0.8
    # photos: area-averaged in linear radiance
    src = read_image(layout["args"]["images"] / "7.JPG")
    expected = cv2.resize(src, (W_IN // 2, H_IN // 2), interpolation=cv2.INTER_AREA)
    assert np.abs(linear_to_srgb(cap.images[6]) - linear_to_srgb(expected)).max() <= 0.5 / 255 + 1e-5


def test_resize_keeps_projection(layout, tmp_path):
    out = tmp_path / "scene"
    run_import(layout, out, size=(W_IN // 2, H_IN // 2))
    cap = load_capture(out)
    full = layout["cams"].select(list(range(V_MASKED)))
    centre = torch.as_tensor(SPHERE_CENTER, dtype=torch.float64)[None]
    xy_full, _ = full.project(centre)
    xy_half, depth = cap.cameras.to(dtype=torch.float64).project(centre)
    assert (depth > 0).all()
    rel_full = xy_full[:, 0] / torch.tensor([W_IN, H_IN], dtype=torch.float64)
    rel_half = xy_half[:, 0] / torch.tensor([W_IN // 2, H_IN // 2], dtype=torch.float64)
    torch.testing.assert_close(rel_half, rel_full, atol=1e-6, rtol=0)

    # and the pixels moved with it: mask centroids (continuous coordinates) scale by exactly 1/2
    def centroids(m):
        ys, xs = np.nonzero(m)
        return np.array([xs.mean() + 0.5, ys.mean() + 0.5])
    for i in range(V_MASKED):
        np.testing.assert_allclose(centroids(cap.masks[i]), centroids(layout["masks"][i]) / 2, atol=0.3)
        x, y = xy_half[i, 0].tolist()
        assert cap.masks[i, int(y), int(x)], "projected object centre falls inside the imported mask"


def test_import_without_resize_keeps_8bit_values(layout, tmp_path):
    out = tmp_path / "scene"
    run_import(layout, out)
    for stem, name in [("1", "1.jpg"), ("7", "7.JPG")]:
        photo = cv2.imread(str(layout["args"]["images"] / name))
        written = cv2.imread(str(out / "images" / f"{stem}.png"))
        np.testing.assert_array_equal(written, photo)
    assert load_capture(out).width == W_IN


def test_inputs_unchanged(layout, tmp_path):
    root = layout["args"]["images"].parent
    before = tree_digest(root)
    run_import(layout, tmp_path / "scene", size=(W_IN // 2, H_IN // 2))
    assert tree_digest(root) == before


def test_camera_folder_with_one_file(layout, tmp_path):
    args = dict(layout["args"], cams=layout["args"]["cams"].parent)
    import_paper(**args, out=tmp_path / "scene", fov_x_deg=FOV)
    assert (tmp_path / "scene" / "scene.json").exists()


# ---- errors ------------------------------------------------------------------------------------
def expect_import_error(layout, out, *fragments, **kw):
    with pytest.raises(LookingGlassError) as info:
        import_paper(**{**layout["args"], "fov_x_deg": FOV, **kw}, out=out)
    message = str(info.value)
    for frag in fragments:
        assert frag in message, f"{frag!r} not in {message!r}"
    assert not out.exists() or not any(out.iterdir()), "a failed import left output behind"
    assert not list(out.parent.glob(f".{out.name}.*")), "a failed import left a temporary folder"
    return message


def test_count_mismatch(layout, tmp_path):
    (layout["args"]["masks"] / "12.png").unlink()
    expect_import_error(layout, tmp_path / "o", "cam12.txt", "11 masks", "12 views")


def test_mask_without_photo(layout, tmp_path):
    (layout["args"]["images"] / "5.jpg").unlink()
    expect_import_error(layout, tmp_path / "o", "5.png", "no photo")


def test_image_mask_size_mismatch(layout, tmp_path):
    cv2.imwrite(str(layout["args"]["masks"] / "3.png"), np.full((H_IN, W_IN - 10), 255, np.uint8))
    expect_import_error(layout, tmp_path / "o", "masks/3.png", f"{W_IN - 10}x{H_IN}", f"3.jpg is {W_IN}x{H_IN}")


def test_empty_mask(layout, tmp_path):
    cv2.imwrite(str(layout["args"]["masks"] / "4.png"), np.zeros((H_IN, W_IN), np.uint8))
    expect_import_error(layout, tmp_path / "o", "masks/4.png", "empty")


def test_unparsable_camera_line(layout, tmp_path):
    cam = layout["args"]["cams"]
    lines = cam.read_text().splitlines()
    assert lines[6].strip() and len(lines[6].split()) == 3  # origin of view 2 (blank lines at 2 and 6)
    lines[6] = "1.0 oops 3.0"
    cam.write_text("\n".join(lines))
    expect_import_error(layout, tmp_path / "o", "cam12.txt", "line 7", "oops")


def test_camera_count_line(layout, tmp_path):
    cam = layout["args"]["cams"]
    cam.write_text(cam.read_text().replace("12\n", "13\n", 1))
    expect_import_error(layout, tmp_path / "o", "cam12.txt", "line 1 says 13 views", "12 views")


def test_read_paper_cameras_tolerates_blank_lines(layout):
    origin, target, up = read_paper_cameras(layout["args"]["cams"])
    assert origin.shape == target.shape == up.shape == (V_MASKED, 3)
    np.testing.assert_array_equal(up, layout["up"][:V_MASKED])


def test_aspect_change_refused(layout, tmp_path):
    expect_import_error(layout, tmp_path / "o", "aspect ratio", "80x60", size=(80, 70))


def test_small_aspect_rounding_allowed(layout, tmp_path):
    # 160x120 -> 81x60: at most 0.4 px off at the image edges (like the paper's 2048x1534 -> 480x360)
    run_import(layout, tmp_path / "o", size=(81, 60))
    assert load_capture(tmp_path / "o").width == 81


def test_non_empty_out_needs_force(layout, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(LookingGlassError, match="not empty"):
        import_paper(**layout["args"], out=out, fov_x_deg=FOV)
    assert (out / "keep.txt").read_text() == "mine"
    import_paper(**layout["args"], out=out, fov_x_deg=FOV, force=True)
    assert not (out / "keep.txt").exists() and (out / "scene.json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o", "paper"]  # no temporary folders left


def test_out_may_not_replace_an_input(layout, tmp_path):
    with pytest.raises(LookingGlassError, match="replace the input"):
        import_paper(**layout["args"], out=layout["args"]["images"].parent, fov_x_deg=FOV, force=True)
    assert layout["args"]["cams"].exists()


def test_camera_order_mismatch_caught_by_scene_checks(layout, tmp_path):
    # a camera file that lists one view facing away is rejected by load_capture's checks
    cam = layout["args"]["cams"]
    origin, target, up = read_paper_cameras(cam)
    target[5] = 2 * origin[5] - target[5]
    lines = [str(V_MASKED)] + [" ".join(map(repr, a[i].tolist())) for i in range(V_MASKED) for a in (origin, target, up)]
    cam.write_text("\n".join(lines))
    expect_import_error(layout, tmp_path / "o", "images/6.png", "behind this camera")


@pytest.mark.parametrize("umask, folder_mode, file_mode", [(0o022, 0o755, 0o644), (0o077, 0o700, 0o600)])
def test_output_has_the_usual_modes(layout, tmp_path, umask, folder_mode, file_mode):
    """The scene folder is made by mkdtemp (0o700) and renamed into place: it, its subfolders and
    its files must get the modes mkdir / open give under the umask, not private ones."""
    import os
    import stat

    out = tmp_path / "scene"
    old = os.umask(umask)
    try:
        run_import(layout, out)
    finally:
        os.umask(old)
    modes = {p.relative_to(out).as_posix(): stat.S_IMODE(p.stat().st_mode) for p in [out, *out.rglob("*")]}
    assert {name for name, m in modes.items() if m != (folder_mode if (out / name).is_dir() else file_mode)} == set()
    assert {"scene.json", "envmap.hdr", "images", "masks/1.png"} <= set(modes)
