"""Real captures (issue 26) on a synthetic capture with known truth (tests/capture_synth.py):
import-colmap, envmap-from-ball and sfm recover what was put in, to the issue's figures."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh

from capture_synth import (distort, log_luminance_correlation, look_at_rig, mirror_ball_photos,
                           write_colmap_text)
from lookingglass.capture.colmap import IMPORT_FILE, import_colmap, read_model
from lookingglass.capture.images import read_envmap, read_image, write_image, write_mask
from lookingglass.capture.scene import load_capture
from lookingglass.data.envmaps import procedural_envmap
from lookingglass.hull import HullConfig, carve_visual_hull
from lookingglass.metrics import shape_metrics
from lookingglass.physics.camera import Cameras
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.render.raycast import object_masks
from lookingglass.render.tracer import RenderConfig, render_views

K1 = -0.06  # SIMPLE_RADIAL distortion of the synthetic camera (barrel, ~2.5 px at a 160x120 corner)
HULL = HullConfig(resolution=64, coarse_resolution=32, subdivision_iterations=2, num_threads=1)


@pytest.fixture(scope="module")
def glass_capture(tmp_path_factory):
    """A tilted torus photographed by 8 distorting cameras (160x120) under a procedural map: photos/,
    masks/ (alpha-channel PNGs for half the views, grey for the others), env.hdr, the true cameras
    as a COLMAP text model (model/), and one extra photo without a mask."""
    root = tmp_path_factory.mktemp("glass")
    mesh = trimesh.creation.torus(major_radius=0.6, minor_radius=0.25)
    mesh.apply_transform(trimesh.transformations.rotation_matrix(0.6, [1, 0, 0.3]))
    mesh.apply_translation([0.3, 1.0, -0.2])  # off the origin: import-colmap must centre it
    env = procedural_envmap(np.random.default_rng(3), 64)
    cams = look_at_rig(8, 0, 3.4, 160, 120, centre=(0.3, 1.0, -0.2))
    result = render_views(mesh, EnvironmentMap(torch.from_numpy(env)), cams.to(dtype=torch.float32),
                          RenderConfig(samples_per_axis=1, threads=1))
    masks = object_masks(mesh, cams, samples_per_axis=2)
    photos = distort(result.image.numpy(), cams, K1)
    dmasks = distort(masks.astype(np.float32), cams, K1) >= 0.5
    names = [f"IMG_{i:02d}" for i in range(len(photos))]
    (root / "masks").mkdir()
    for i, (name, img, m) in enumerate(zip(names, photos, dmasks)):
        write_image(root / "photos" / f"{name}.png", img)
        if i % 2:
            write_mask(root / "masks" / f"{name}.png", m)
        else:  # the paper's release: the mask in a PNG's alpha channel
            rgba = np.concatenate([np.full(m.shape + (3,), 128, np.uint8), (m * 255).astype(np.uint8)[..., None]], -1)
            cv2.imwrite(str(root / "masks" / f"{name}.png"), rgba)
    write_image(root / "photos" / "IMG_99.png", photos[0])  # no mask: skipped with a warning
    write_image(root / "env.hdr", env)
    write_colmap_text(root / "model", cams, [f"{n}.png" for n in names], K1)
    return dict(root=root, mesh=mesh, cams=cams, masks=masks, env=env, names=names)


def test_import_colmap_hull_matches_true_cameras(glass_capture, tmp_path):
    g = glass_capture
    root = g["root"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import_colmap(root / "model", root / "photos", root / "masks", root / "env.hdr", tmp_path / "scene")
    assert any("IMG_99.png" in str(w.message) and "without a mask" in str(w.message) for w in caught)
    cap = load_capture(tmp_path / "scene")
    assert [Path(v.image).stem for v in cap.spec.views] == g["names"]
    record = json.loads((tmp_path / "scene" / IMPORT_FILE).read_text())
    R = np.array(record["world_from_model"]["rotation"])
    c = np.array(record["world_from_model"]["centre"])
    # centred and upright: the torus's centre near the origin, +y the true up
    assert np.linalg.norm(c - [0.3, 1.0, -0.2]) < 0.1, c
    assert math.degrees(math.acos(R[1] @ [0, 1, 0])) < 3.0
    # the hull from the imported scene against the one from the true cameras, same GT
    gt_scene = g["mesh"].copy()
    gt_scene.apply_translation(-c)
    gt_scene.apply_transform(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    true_hull = carve_visual_hull(g["masks"], g["cams"].to(dtype=torch.float32), HULL).mesh
    imported_hull = carve_visual_hull(cap.masks, cap.cameras, HULL).mesh
    cd_true = shape_metrics(true_hull, g["mesh"], samples=5000)["cd"]
    cd_imported = shape_metrics(imported_hull, gt_scene, samples=5000)["cd"]
    print(f"hull CD x1e4: true cameras {cd_true:.2f}, import-colmap {cd_imported:.2f}")
    assert cd_imported <= 1.1 * cd_true, (cd_true, cd_imported)
    # the map's frame follows the world's: E_scene(R d) == E_true(d)
    # seeded and 20 000 directions: 2000 unseeded ones gave 0.966-0.992 with the test order (0.983 at 200 000)
    d = torch.randn(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    d = torch.nn.functional.normalize(d, dim=-1)
    true = EnvironmentMap(torch.from_numpy(g["env"]).double()).lookup(d)
    scene = EnvironmentMap(torch.from_numpy(cap.envmap).double()).lookup(d @ torch.from_numpy(R).T)
    assert log_luminance_correlation(true.numpy()[None], scene.numpy()[None]) > 0.97


def test_import_colmap_uses_each_camera_of_the_model(tmp_path):
    """A COLMAP model whose photos come from two cameras of one size (fov 55 and 46 degrees,
    distortion -0.06 and -0.01): each photo is undistorted with its own camera, the scene keeps each
    view's fov, and the hull matches the one from the true cameras."""
    torus = trimesh.creation.torus(major_radius=0.6, minor_radius=0.25)
    rig = look_at_rig(8, 2, 3.4, 160, 120)
    fov = np.where(np.arange(8) < 4, 55.0, 46.0)
    k = np.where(np.arange(8) < 4, -0.06, -0.01)
    p = rig.look_at_params()
    cams = Cameras.look_at(p["origin"], p["target"], p["up"], fov, 160, 120, dtype=torch.float64)
    masks = object_masks(torus, cams, samples_per_axis=2)
    dmasks = distort(masks.astype(np.float32), cams, k)
    for i, m in enumerate(dmasks):
        write_image(tmp_path / "photos" / f"V{i}.png", np.repeat(m[..., None], 3, -1) * 0.8 + 0.1)
        write_mask(tmp_path / "masks" / f"V{i}.png", m >= 0.5)
    write_image(tmp_path / "env.hdr", np.ones((16, 32, 3), np.float32))
    write_colmap_text(tmp_path / "model", cams, [f"V{i}.png" for i in range(8)], k)
    model = read_model(tmp_path / "model")
    assert len({tuple(v.camera.params) for v in model.views}) == 2
    import_colmap(tmp_path / "model", tmp_path / "photos", tmp_path / "masks", tmp_path / "env.hdr", tmp_path / "scene")
    cap = load_capture(tmp_path / "scene")
    assert np.allclose([v.fov_x_deg for v in cap.spec.views], fov, atol=1e-6)
    R = np.array(json.loads((tmp_path / "scene" / IMPORT_FILE).read_text())["world_from_model"]["rotation"])
    c = np.array(json.loads((tmp_path / "scene" / IMPORT_FILE).read_text())["world_from_model"]["centre"])
    gt_scene = torus.copy().apply_translation(-c).apply_transform(np.block([[R, np.zeros((3, 1))],
                                                                             [np.zeros((1, 3)), np.ones((1, 1))]]))
    cd_true = shape_metrics(carve_visual_hull(masks, cams.to(dtype=torch.float32), HULL).mesh, torus, samples=5000)["cd"]
    cd = shape_metrics(carve_visual_hull(cap.masks, cap.cameras, HULL).mesh, gt_scene, samples=5000)["cd"]
    print(f"two cameras: hull CD x1e4 {cd:.2f} against {cd_true:.2f} from the true cameras")
    assert cd <= 1.1 * cd_true, (cd, cd_true)


BALL_CENTRE, BALL_RADIUS = np.array([0.2, 0.9, -0.1]), 0.25


@pytest.fixture(scope="module")
def ball_capture(tmp_path_factory):
    """8 HDR photos (400x300, EXR, distorting camera) of a mirror ball (reflectance 0.8) under a
    procedural map, the true cameras as a COLMAP model, and circles as a user would click them (the
    projected centre and radius rounded to whole pixels)."""
    root = tmp_path_factory.mktemp("ball")
    env = procedural_envmap(np.random.default_rng(5), 128)
    cams = look_at_rig(8, 1, 2.0, 400, 300, fov_x_deg=50, centre=BALL_CENTRE)
    photos = distort(mirror_ball_photos(env, cams, BALL_CENTRE, BALL_RADIUS, 0.8, samples_per_axis=2), cams, K1)
    names = [f"ball_{i}" for i in range(len(photos))]
    for name, img in zip(names, photos):
        write_image(root / "ball" / f"{name}.exr", img)
    write_colmap_text(root / "model", cams, [f"{n}.exr" for n in names], K1)
    xy, depth = cams.project(torch.from_numpy(BALL_CENTRE)[None])
    f = cams.width / (2 * float(cams.tan_half_fov_x[0]))
    r = f * np.tan(np.arcsin(BALL_RADIUS / depth[:, 0].numpy()))
    (root / "circles.txt").write_text("".join(f"{n} {round(x)} {round(y)} {round(rr)}\n"
                                              for n, (x, y), rr in zip(names, xy[:, 0].tolist(), r)))
    return dict(root=root, env=env, cams=cams, names=names)


@pytest.mark.parametrize("circles", [True, False], ids=["circles-file", "detected"])
def test_envmap_from_ball_recovers_ball_and_map(ball_capture, tmp_path, circles):
    """With the clicked circles, and with the ball detected in every photo (one sphere all views
    agree on)."""
    from lookingglass.capture.ball import envmap_from_ball
    from lookingglass.data.envmaps import resize_envmap

    root = ball_capture["root"]
    record = envmap_from_ball(root / "model", root / "ball", tmp_path / "env.hdr",
                              circles=root / "circles.txt" if circles else None, size=(256, 128))
    err = np.linalg.norm(np.array(record["centre"]) - BALL_CENTRE) / BALL_RADIUS
    rad = abs(record["radius"] / BALL_RADIUS - 1)
    est = read_envmap(tmp_path / "env.hdr")
    corr = log_luminance_correlation(est, resize_envmap(ball_capture["env"], 128))
    residuals = [v["residual_px"] for v in record["views"]]
    print(f"ball centre error {100 * err:.2f}% of r, radius error {100 * rad:.2f}%, envmap log-lum corr {corr:.3f}, "
          f"residuals px {np.round(residuals, 2).tolist()}")
    assert err < 0.01 and rad < 0.015
    assert corr >= 0.9
    assert (tmp_path / "env.preview.png").is_file() and len(record["views"]) == 8
    assert {v["circle_from"] for v in record["views"]} == {"circles file" if circles else "detected"}


def test_ball_found_among_decoys(ball_capture, tmp_path):
    """Each ball photo gets three discs drawn beside the ball, larger and sharper-edged than it (the
    single-photo detector takes a disc in some photos): the calibration still finds the ball in every
    photo; a photo whose ball is painted over, or whose clicked circle is off the ball, is refused by
    name."""
    from lookingglass.capture.ball import detect_ball, envmap_from_ball, read_circles
    from lookingglass.errors import LookingGlassError

    root = ball_capture["root"]
    truth = read_circles(root / "circles.txt")
    rng = np.random.default_rng(11)
    lone_misses = 0
    for name in ball_capture["names"]:
        img = read_image(root / "ball" / f"{name}.exr")
        cx, cy, r = truth[name]
        placed: list[tuple[float, float, float]] = [(cx, cy, r)]
        while len(placed) < 4:  # three discs, clear of the ball, of each other and of the border
            rd = float(rng.uniform(1.0, 1.25)) * r
            x, y = rng.uniform(rd + 2, img.shape[1] - rd - 2), rng.uniform(rd + 2, img.shape[0] - rd - 2)
            if all(math.hypot(x - a, y - b) > rd + c + 4 for a, b, c in placed):
                placed.append((x, y, rd))
                shade = float(img.mean()) * float(rng.choice([0.1, 4.0]))
                cv2.circle(img, (round(x * 16 - 8), round(y * 16 - 8)), round(rd * 16), (shade,) * 3, -1,
                           lineType=cv2.LINE_AA, shift=4)
        write_image(tmp_path / "ball" / f"{name}.exr", img)
        found = detect_ball(img)
        lone_misses += found is None or math.hypot(found[0] - cx, found[1] - cy) > 3
    record = envmap_from_ball(root / "model", tmp_path / "ball", tmp_path / "env.hdr", size=(64, 32))
    errors = [max(math.hypot(v["circle"][0] - truth[Path(v["photo"]).stem][0],
                             v["circle"][1] - truth[Path(v["photo"]).stem][1]),
                  abs(v["circle"][2] - truth[Path(v["photo"]).stem][2])) for v in record["views"]]
    err = np.linalg.norm(np.array(record["centre"]) - BALL_CENTRE) / BALL_RADIUS
    print(f"decoys: the lone detector misses {lone_misses} of 8 balls; with the calibration circle errors px "
          f"{np.round(errors, 2).tolist()}, centre error {100 * err:.2f}% of r")
    assert lone_misses >= 1 and max(errors) < 2.0 and err < 0.01
    # the ball painted over in one photo (the discs remain): that photo is named
    img = read_image(tmp_path / "ball" / "ball_3.exr")
    cx, cy, r = truth["ball_3"]
    cv2.circle(img, (round(cx - 0.5), round(cy - 0.5)), round(1.3 * r), (float(np.median(img)),) * 3, -1)
    write_image(tmp_path / "ball" / "ball_3.exr", img)
    with pytest.raises(LookingGlassError, match="mirror ball not found in this photo") as caught:
        envmap_from_ball(root / "model", tmp_path / "ball", tmp_path / "env2.hdr", size=(64, 32))
    assert "ball_3.exr" in str(caught.value) and not (tmp_path / "env2.hdr").exists()
    # a clicked circle off the ball (the others right) is named too
    (tmp_path / "circles.txt").write_text("".join(f"{n} {cx + 25 * (n == 'ball_5')} {cy} {r}\n"
                                                  for n, (cx, cy, r) in truth.items()))
    with pytest.raises(LookingGlassError, match="circle in the circles file is not on the sphere") as caught:
        envmap_from_ball(root / "model", root / "ball", tmp_path / "env3.hdr", circles=tmp_path / "circles.txt")
    assert "ball_5.exr" in str(caught.value)
    # a circle far larger than the photo (a typo) is named as such, not as a sphere that does not fit
    (tmp_path / "circles.txt").write_text("".join(f"{n} {cx} {cy} {1e9 if n == 'ball_2' else r}\n"
                                                  for n, (cx, cy, r) in truth.items()))
    with pytest.raises(LookingGlassError, match="does not fit this") as caught:
        envmap_from_ball(root / "model", root / "ball", tmp_path / "env4.hdr", circles=tmp_path / "circles.txt")
    assert "ball_2.exr" in str(caught.value) and "1e+09" in str(caught.value)


def test_cli_envmap_from_ball_then_import_colmap(ball_capture, glass_capture, tmp_path):
    """The two commands chained as a user would, through the command line: the ball's map (a config
    flag given) becomes the scene's envmap, rotated into the scene's frame."""
    from cli_helpers import run

    b, g = ball_capture["root"], glass_capture["root"]
    proc = run("envmap-from-ball", "--model", b / "model", "--images", b / "ball", "--circles", b / "circles.txt",
               "--out", tmp_path / "env.hdr", "--size", 64, 32, "--ball.reflectance", 0.8)
    assert "wrote" in proc.stderr and (tmp_path / "env.ball.json").is_file()
    run("import-colmap", "--model", g / "model", "--images", g / "photos", "--masks", g / "masks",
        "--envmap", tmp_path / "env.hdr", "--out", tmp_path / "scene", "--size", 80, 60, "--up", 0, 1, 0)
    cap = load_capture(tmp_path / "scene")
    assert cap.num_views == 8 and (cap.width, cap.height) == (80, 60) and cap.envmap.shape == (32, 64, 3)
    record = json.loads((tmp_path / "scene" / IMPORT_FILE).read_text())
    assert record["up_from"] == "--up" and np.allclose(record["world_from_model"]["rotation"][1], [0, 1, 0])


def test_ball_detection_finds_the_ball(ball_capture):
    """OpenCV's Hough circles, refined onto the outline, against the clicked (true, rounded) circles."""
    from lookingglass.capture.ball import detect_ball, read_circles
    from lookingglass.capture.images import read_image

    root = ball_capture["root"]
    truth = read_circles(root / "circles.txt")
    errors = []
    for name in ball_capture["names"]:
        found = detect_ball(read_image(root / "ball" / f"{name}.exr"))
        cx, cy, r = truth[name]
        errors.append(np.inf if found is None else max(math.hypot(found[0] - cx, found[1] - cy), abs(found[2] - r)))
    print(f"ball detection error px: {np.round(errors, 2).tolist()}")
    assert max(errors) < 3.0, errors


@pytest.mark.slow
def test_capture_end_to_end(tmp_path):
    """`lookingglass capture` on a whole synthetic shoot (`capture_shoot`: 9 photos of a glass sphere
    and 3 of a mirror ball at its place, 480x360, a room papered with discs), the ball detected (no
    circles file), reconstruct stopped after the visual hull. All 12 photos register; after the
    similarity mapping the recovered camera centres onto the true ones, rotations are within 0.5 deg
    and centres within 1% of the camera distance, the ball's centre within 3% of its radius (the
    camera centres' own error is up to 5% of it); the hull, mapped into the true frame, is within 50%
    (CD, see below) of the hull carved from the true cameras at the same settings, and fitted onto the
    object (ICP, as the true cameras' hull), within 10% of it (the issue's bar); a rerun skips every
    stage, and `sfm` rerun skips extraction and matching."""
    from capture_synth import capture_figures, capture_shoot
    from cli_helpers import run
    from lookingglass.capture.sfm import run_sfm
    from lookingglass.capture.workflow import run_capture
    from lookingglass.progress import Reporter

    truth = capture_shoot(tmp_path, 12, (2, 6, 9), 480, 360)
    run("capture", "--photos", tmp_path / "photos", "--ball", tmp_path / "ball", "--masks", tmp_path / "masks",
        "--out", tmp_path / "work", "--size", 160, 120, "--envmap-size", 64, 32, "--ball.reflectance", 0.8,
        "--stop-after", "visual_hull")
    work = tmp_path / "work"
    sfm = json.loads((work / "sfm" / "sfm.json").read_text())
    assert sfm["unregistered"] == [], sfm
    f = capture_figures(truth, work, (160, 120))
    model, rot_err, centre_err = f["model"], f["rotation_err_deg"], f["centre_err"]
    assert {v["circle_from"] for v in f["ball_fit"]["views"]} == {"detected"}
    cd, cd_true, cd_fit, cd_true_fit = (f["hull_cd"], f["hull_cd_true_cameras"], f["hull_cd_fitted"],
                                        f["hull_cd_true_cameras_fitted"])
    print(f"capture: rotation error max {rot_err.max():.3f} deg, centre error max {100 * centre_err.max():.3f}%, ball "
          f"centre error {100 * f['ball_centre_err']:.2f}% of r, radius {100 * f['ball_radius_err']:+.2f}%, residuals px "
          f"{np.round(f['residuals_px'], 2).tolist()}, map log-luminance correlation {f['envmap_corr']:.3f}; hull CD "
          f"x1e4 {cd:.2f} against {cd_true:.2f} from the true cameras; fitted onto the object: {cd_fit:.2f} against "
          f"{cd_true_fit:.2f}")
    assert rot_err.max() < 0.5 and centre_err.max() < 0.01
    assert f["ball_centre_err"] < 0.03 and max(f["residuals_px"]) < 3.0
    # At this size (3 ball photos of 480x360, 160x120 masks) the map is a 64x32 median of three views.
    assert f["envmap_corr"] >= 0.85, f["envmap_corr"]
    # Where the similarity puts it, 50%: that similarity is fitted to camera centres 0.5-0.8% of the
    # camera distance off (~0.5 px in these 160x120 masks, where the object's radius is 17 px), and
    # moves the hull with them: +18% here (+16% to +27% in five runs before RANSAC was seeded). The
    # shape itself, fitted onto the object as the true cameras' hull is: +3.9% (+4.8% to +10.0%).
    assert cd <= 1.5 * cd_true, (cd, cd_true)
    assert cd_fit <= 1.1 * cd_true_fit, (cd_fit, cd_true_fit)
    reporter = Reporter(quiet=True)
    reporter.info = lambda message: reporter.stages.append({"name": "info", "message": message})
    run_capture(tmp_path / "photos", tmp_path / "ball", tmp_path / "masks", work, reporter=reporter)  # in-process
    assert sum("skipped" in st.get("message", "") for st in reporter.stages) == 4, reporter.stages
    # sfm on its own again: extraction and matching are not redone, the mapping is
    reporter = Reporter(quiet=True)
    record = run_sfm([tmp_path / "photos", tmp_path / "ball"], work / "sfm", tmp_path / "masks", reporter=reporter)
    assert [st["name"] for st in reporter.stages] == ["mapping"] and record["unregistered"] == []
    # seeded (RANSAC and the mapper): the same poses again, to the bit
    again = read_model(work / "sfm")
    assert all(np.array_equal(a.origin, b.origin) for a, b in zip(model.views, again.views))
