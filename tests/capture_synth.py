"""A synthetic real capture with known truth, for the real-capture tests (issue 26): photos taken by a
radially distorting camera (COLMAP's SIMPLE_RADIAL) of a glass object, of a mirror ball and of a
textured room, under a known environment map; the true cameras as a COLMAP text model.

Everything is made with the project's own physics: `Cameras` rays, `EnvironmentMap.lookup`, the
glass renderer `render_views` and `object_masks`; the distortion is COLMAP's own equations
(pycolmap `Camera.cam_from_img`) applied with `cv2.remap`.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import torch
import trimesh
from scipy.spatial.transform import Rotation

from lookingglass.physics.camera import Cameras
from lookingglass.physics.environment import EnvironmentMap

OBJECT_CENTRE, OBJECT_RADIUS = (0.0, -0.1, 0.0), 0.3  # the glass sphere of `capture_shoot`, and its ball


def colmap_camera(cameras: Cameras, k: float, view: int = 0) -> pycolmap.Camera:
    """The SIMPLE_RADIAL camera of `cameras`' view `view`: its focal length and size, centred,
    distortion k."""
    f = cameras.width / (2 * float(cameras.tan_half_fov_x[view]))
    return pycolmap.Camera(model="SIMPLE_RADIAL", width=cameras.width, height=cameras.height,
                           params=[f, cameras.width / 2, cameras.height / 2, k])


def _per_view(k, cameras: Cameras) -> list[float]:
    """A distortion per view: k itself when it is one number (one shared camera)."""
    return [float(k)] * cameras.num_views if np.ndim(k) == 0 else [float(v) for v in k]


def cam_from_world(cameras: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP poses of our cameras: R (V, 3, 3) rows (right, -up, forward), t (V, 3) = -R origin."""
    basis = cameras.basis.double().numpy()
    R = basis * np.array([1.0, -1.0, 1.0])[None, :, None]
    t = -np.einsum("vij,vj->vi", R, cameras.origin.double().numpy())
    return R, t


def write_colmap_text(folder: Path, cameras: Cameras, names: list[str], k) -> Path:
    """The true cameras as a COLMAP text model in `folder`: one SIMPLE_RADIAL camera per distinct
    (focal length, distortion) among the views (one shared camera when k is one number and the fovs
    agree); k: distortion, one number or one per view."""
    folder.mkdir(parents=True, exist_ok=True)
    cams = [colmap_camera(cameras, kv, i) for i, kv in enumerate(_per_view(k, cameras))]
    ids: dict[tuple, int] = {}
    for cam in cams:
        ids.setdefault(tuple(np.round(cam.params, 9)), len(ids) + 1)
    (folder / "cameras.txt").write_text("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
        f"{i} SIMPLE_RADIAL {cameras.width} {cameras.height} " + " ".join(f"{p:.12g}" for p in params) + "\n"
        for params, i in ids.items()))
    R, t = cam_from_world(cameras)
    lines = []
    for i, name in enumerate(names):
        x, y, z, w = Rotation.from_matrix(R[i]).as_quat()
        lines += [f"{i + 1} {w:.15g} {x:.15g} {y:.15g} {z:.15g} " + " ".join(f"{v:.15g}" for v in t[i])
                  + f" {ids[tuple(np.round(cams[i].params, 9))]} {name}", ""]
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text("")
    return folder


def distort(images: np.ndarray, cameras: Cameras, k) -> np.ndarray:
    """Pinhole renders (V, H, W[, C]) of `cameras` as SIMPLE_RADIAL cameras with distortion k (one
    number, or one per view) see them: each distorted pixel takes the pinhole image at its
    undistorted ray (bilinear)."""
    W, H = cameras.width, cameras.height
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    out = []
    for view, (img, kv) in enumerate(zip(images, _per_view(k, cameras))):  # views, not pixels
        cam = colmap_camera(cameras, kv, view)
        norm = np.asarray(cam.cam_from_img(np.stack([xs.ravel(), ys.ravel()], -1)))  # (N, 2)
        f = cam.params[0]
        mx = (norm[:, 0] * f + W / 2 - 0.5).reshape(H, W).astype(np.float32)
        my = (norm[:, 1] * f + H / 2 - 0.5).reshape(H, W).astype(np.float32)
        out.append(cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))
    return np.stack(out)


def look_at_rig(num_views: int, seed: int, distance: float, width: int, height: int, fov_x_deg: float = 55.0,
                centre=(0.0, 0.0, 0.0), heights=(20.0, -15.0)) -> Cameras:
    """Cameras around `centre` at two heights (elevations in degrees), random azimuths and small
    target jitter and roll: a hand-held shoot of one spot."""
    rng = np.random.default_rng(seed)
    az = np.linspace(0, 2 * math.pi, num_views, endpoint=False) + rng.uniform(-0.2, 0.2, num_views)
    el = np.radians(np.array([heights[i % 2] for i in range(num_views)]) + rng.uniform(-5, 5, num_views))
    dirs = np.stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)], -1)
    c = np.asarray(centre, np.float64)
    origin = c + distance * dirs * rng.uniform(0.9, 1.1, (num_views, 1))
    target = c + rng.uniform(-0.05, 0.05, (num_views, 3)) * distance
    up = np.array([0.0, 1.0, 0.0]) + rng.uniform(-0.08, 0.08, (num_views, 3))
    return Cameras.look_at(origin, target, up, fov_x_deg, width, height, dtype=torch.float64)


def _supersampled(cameras: Cameras, shade, samples_per_axis: int) -> np.ndarray:
    """Box-filtered image (V, H, W, 3): shade(origins (V, H, W, 3), dirs (V, H, W, 3)) averaged over
    s x s sub-pixel rays."""
    s = samples_per_axis
    acc = 0.0
    for i in range(s):
        for j in range(s):
            o, d = cameras.pixel_rays(subpixel=((j + 0.5) / s, (i + 0.5) / s))
            acc = acc + shade(o, d)
    return (acc / (s * s)).numpy().astype(np.float32)


def mirror_ball_photos(envmap: np.ndarray, cameras: Cameras, centre, radius: float, reflectance: float = 0.8,
                       samples_per_axis: int = 3) -> np.ndarray:
    """Pinhole photos (V, H, W, 3) linear of a perfect mirror sphere (reflectance) under `envmap`
    (distant, also seen behind the ball)."""
    env = EnvironmentMap(torch.as_tensor(envmap, dtype=torch.float64))
    c = torch.as_tensor(centre, dtype=torch.float64)

    def shade(o, d):
        oc = o - c
        b = (oc * d).sum(-1)
        disc = b * b - ((oc * oc).sum(-1) - radius ** 2)
        hit = (disc > 0) & (-b - disc.clamp(min=0).sqrt() > 0)
        t = -b - disc.clamp(min=0).sqrt()
        n = torch.nn.functional.normalize(o + t[..., None] * d - c, dim=-1)
        refl = d - 2 * (d * n).sum(-1, keepdim=True) * n
        return torch.where(hit[..., None], reflectance * env.lookup(refl), env.lookup(d))

    return _supersampled(cameras.to(dtype=torch.float64), shade, samples_per_axis)


def room_texture(seed: int, size: int = 1024) -> np.ndarray:
    """A grey wall (size, size) in [0.05, 1] covered with random discs and boxes of random shades:
    sharp, unrepeated corners for SIFT at every scale."""
    rng = np.random.default_rng(seed)
    tex = np.full((size, size), 0.5, np.float32)
    for _ in range(600):
        shade = float(rng.uniform(0.05, 1.0))
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(size // 100, size // 12))
        if rng.random() < 0.5:
            cv2.circle(tex, (x, y), r, shade, -1, lineType=cv2.LINE_AA)
        else:
            cv2.rectangle(tex, (x - r, y - r // 2), (x + r, y + r // 2), shade, -1, lineType=cv2.LINE_AA)
    return tex


def room_photos(cameras: Cameras, half_size: float = 4.0, seed: int = 0, samples_per_axis: int = 2,
                table=((-0.8, -0.9, -0.8), (0.8, -0.4, 0.8))) -> np.ndarray:
    """Pinhole photos (V, H, W, 3) from inside a cube room |p|_inf <= half_size whose six walls, and
    the faces of a box ("table": its min and max corners) standing in it, carry random textures."""
    textures = torch.from_numpy(np.stack([room_texture(seed * 12 + k) for k in range(12)]))  # (12, S, S)
    S = textures.shape[-1]
    lo, hi = torch.tensor(table[0], dtype=torch.float64), torch.tensor(table[1], dtype=torch.float64)
    others = torch.tensor([[1, 2], [0, 2], [0, 1]])

    def texel(p, axis, wall, low, high):
        uv = (torch.gather(p, -1, others[axis]) - torch.gather(low.expand_as(p), -1, others[axis])) \
            / torch.gather((high - low).expand_as(p), -1, others[axis])
        ij = (uv.clamp(0, 1 - 1e-6) * S).long()
        return textures[wall, ij[..., 1], ij[..., 0]]

    def shade(o, d):
        safe = torch.where(d.abs() > 1e-12, d, torch.full_like(d, 1e-12))
        t_room, axis = ((torch.sign(d) * half_size - o) / safe).min(dim=-1)
        p = o + t_room[..., None] * d
        wall = axis * 2 + (torch.gather(d, -1, axis[..., None])[..., 0] > 0).long()
        value = texel(p, axis, wall, torch.full((3,), -half_size, dtype=torch.float64),
                      torch.full((3,), half_size, dtype=torch.float64))
        t1, t2 = (lo - o) / safe, (hi - o) / safe
        near, far = torch.minimum(t1, t2), torch.maximum(t1, t2)
        t_in, face = near.max(dim=-1)
        hit = (t_in <= far.min(dim=-1).values) & (t_in > 0)
        q = o + t_in[..., None] * d
        side = 6 + face * 2 + (torch.gather(d, -1, face[..., None])[..., 0] < 0).long()
        value = torch.where(hit, texel(q, face, side, lo, hi), value)
        return value[..., None].expand(*value.shape, 3).double()

    return _supersampled(cameras.to(dtype=torch.float64), shade, samples_per_axis)


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: s, R, t with dst ~ s R src + t (points (N, 3)), e.g. recovered camera centres onto
    the true ones."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / (a ** 2).sum(1).mean()
    return s, R, md - s * R @ ms


def fitted_onto(mesh: trimesh.Trimesh, target: trimesh.Trimesh, samples: int = 4000) -> trimesh.Trimesh:
    """`mesh` moved rigidly onto `target` by ICP from where it is (points sampled on it, closest points on
    the target): how good a shape is, apart from where the capture's arbitrary frame put it."""
    points = mesh.sample(samples, seed=0)
    matrix, _, _ = trimesh.registration.icp(points, target, initial=np.eye(4), max_iterations=50, threshold=1e-7,
                                            reflection=False, scale=False)
    return mesh.copy().apply_transform(matrix)


def log_luminance_correlation(a: np.ndarray, b: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Pearson correlation of log luminance of two (H, 2H, 3) maps, solid-angle weighted, over `valid`."""
    lum = lambda x: np.log(np.maximum(x @ np.array([0.2126, 0.7152, 0.0722]), 1e-4))  # noqa: E731
    H = a.shape[0]
    w = np.repeat(np.sin(np.pi * (np.arange(H) + 0.5) / H)[:, None], a.shape[1], 1)
    if valid is not None:
        w = w * valid
    la, lb = lum(a), lum(b)
    ma, mb = (w * la).sum() / w.sum(), (w * lb).sum() / w.sum()
    cov = (w * (la - ma) * (lb - mb)).sum()
    return float(cov / math.sqrt((w * (la - ma) ** 2).sum() * (w * (lb - mb) ** 2).sum()))


def capture_shoot(root: Path, num_views: int = 16, ball_views: tuple[int, ...] = (2, 5, 10, 13), width: int = 640,
                  height: int = 480, k: float = -0.05, seed: int = 4) -> dict:
    """A whole shoot as a user brings it to `lookingglass capture`: a glass sphere on a textured table in
    a room papered with discs and boxes (a trap for a circle detector), photographed by `num_views`
    SIMPLE_RADIAL cameras (distortion k) at two heights; the views in `ball_views` see a mirror ball
    (reflectance 0.8) where the object stands instead. Writes ROOT/photos/obj_NN.png, masks/obj_NN.png,
    ball/ball_NN.exr. Returns the truth: cams (all views), object and ball view indices, the object's
    mesh, the environment map (the ball's and the object's light, true frame)."""
    import trimesh

    from lookingglass.capture.images import write_image, write_mask
    from lookingglass.data.envmaps import procedural_envmap
    from lookingglass.render.raycast import object_masks
    from lookingglass.render.tracer import RenderConfig, render_views

    env = procedural_envmap(np.random.default_rng(7), 64)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=OBJECT_RADIUS).apply_translation(OBJECT_CENTRE)
    cams = look_at_rig(num_views, seed, 2.5, width, height, fov_x_deg=60, heights=(35.0, 15.0))
    ball_idx = [i for i in range(num_views) if i in ball_views]
    obj_idx = [i for i in range(num_views) if i not in ball_idx]
    room = room_photos(cams)
    glass = render_views(mesh, EnvironmentMap(torch.from_numpy(env)), cams.select(obj_idx).to(dtype=torch.float32),
                         RenderConfig(samples_per_axis=1, threads=1))
    masks = glass.mask.numpy()
    photos = np.where(masks[..., None], glass.image.numpy(), room[obj_idx])
    balls = mirror_ball_photos(env, cams.select(ball_idx), OBJECT_CENTRE, OBJECT_RADIUS, 0.8, samples_per_axis=1)
    ball_masks = object_masks(trimesh.creation.icosphere(subdivisions=4, radius=OBJECT_RADIUS)
                              .apply_translation(OBJECT_CENTRE), cams.select(ball_idx))
    balls = np.where(ball_masks[..., None], balls, room[ball_idx])
    for i, img, m in zip(obj_idx, distort(photos, cams.select(obj_idx), k),
                         distort(masks.astype(np.float32), cams.select(obj_idx), k) >= 0.5):
        write_image(root / "photos" / f"obj_{i:02d}.png", img)
        write_mask(root / "masks" / f"obj_{i:02d}.png", m)
    for i, img in zip(ball_idx, distort(balls, cams.select(ball_idx), k)):
        write_image(root / "ball" / f"ball_{i:02d}.exr", img)
    return dict(cams=cams, obj_idx=obj_idx, ball_idx=ball_idx, mesh=mesh, env=env, masks=masks)


def capture_figures(truth: dict, work: Path, scene_size: tuple[int, int]) -> dict:
    """Issue 26's figures for a `lookingglass capture` run in `work` on the shoot `truth` (`capture_shoot`'s), after the
    similarity that maps the recovered camera centres onto the true ones: each view's rotation error (deg) and
    centre error (fraction of the mean camera distance), the ball's centre error (fraction of its radius) and radius
    error (relative), each ball view's outline residual (px), the map's log-luminance correlation with the truth,
    the visual hull's CD in the true frame, that of the hull carved from the true cameras at the same settings
    (`scene_size` masks), and both after fitting onto the object (ICP). Also the model, its views' indices and the
    similarity (s, R, t)."""
    import json

    from lookingglass.capture.colmap import IMPORT_FILE, read_model
    from lookingglass.capture.images import read_envmap
    from lookingglass.data.envmaps import resize_envmap
    from lookingglass.hull import carve_visual_hull
    from lookingglass.metrics import shape_metrics
    from lookingglass.physics.environment import rotate_envmap
    from lookingglass.presets import preset
    from lookingglass.render.raycast import object_masks

    model = read_model(work / "sfm")
    index = [int(v.stem.split("_")[1]) for v in model.views]
    cams = truth["cams"].select(index)
    est_o, true_o = np.stack([v.origin for v in model.views]), cams.origin.numpy()
    s, R, t = similarity(est_o, true_o)
    distance = np.linalg.norm(true_o - true_o.mean(0), axis=1).mean()
    centre_err = np.linalg.norm((s * est_o @ R.T + t) - true_o, axis=1) / distance
    rot_err = np.array([math.degrees(math.acos(np.clip((np.trace(R @ v.basis.T @ b) - 1) / 2, -1, 1)))
                        for v, b in zip(model.views, cams.basis.numpy())])
    ball_fit = json.loads((work / "envmap.ball.json").read_text())
    est_env = rotate_envmap(torch.from_numpy(read_envmap(work / "envmap.hdr")).double(), torch.from_numpy(R)).numpy()
    # the hull: scene frame -> model frame (import.json) -> true frame (the similarity)
    frame = json.loads((work / "scene" / IMPORT_FILE).read_text())["world_from_model"]
    hull = trimesh.load(work / "result" / "visual_hull.ply")
    p_model = hull.vertices @ np.array(frame["rotation"]) + frame["centre"]
    hull = trimesh.Trimesh(s * p_model @ R.T + t, hull.faces, process=False)
    true_cams = truth["cams"].select(truth["obj_idx"]).with_resolution(*scene_size)
    true_hull = carve_visual_hull(object_masks(truth["mesh"], true_cams), true_cams.to(dtype=torch.float32),
                                  preset().pipeline.hull).mesh
    return dict(model=model, index=index, similarity=(s, R, t), rotation_err_deg=rot_err, centre_err=centre_err,
                ball_fit=ball_fit,
                ball_centre_err=float(np.linalg.norm(s * R @ ball_fit["centre"] + t - OBJECT_CENTRE) / OBJECT_RADIUS),
                ball_radius_err=float(s * ball_fit["radius"] / OBJECT_RADIUS - 1),
                residuals_px=[v["residual_px"] for v in ball_fit["views"]],
                envmap_corr=log_luminance_correlation(est_env, resize_envmap(truth["env"], est_env.shape[0])),
                hull_cd=shape_metrics(hull, truth["mesh"])["cd"],
                hull_cd_true_cameras=shape_metrics(true_hull, truth["mesh"])["cd"],
                hull_cd_fitted=shape_metrics(fitted_onto(hull, truth["mesh"]), truth["mesh"])["cd"],
                hull_cd_true_cameras_fitted=shape_metrics(fitted_onto(true_hull, truth["mesh"]), truth["mesh"])["cd"])
