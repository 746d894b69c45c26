"""Gather a reconstruction into the figures, pictures and meshes report.html shows (page.py lays
them out)."""

from __future__ import annotations

import base64
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh

from ..capture.images import exposure_factor, linear_to_srgb, srgb_to_linear
from ..errors import LookingGlassError
from ..fileio import read_json, write_atomic

REPORT_NAME = "report.html"
PANEL = 192  # pixels of one per-view picture (a square around the object)
# Faces each mesh keeps in the 3D view; larger meshes are decimated for display only (a 10-view
# report then stays near 4 MB whatever the meshes' size).
DISPLAY_FACES = {"mesh": 80000, "ground_truth": 60000, "visual_hull": 20000}
# the distance colour map (display sRGB, pale where the result meets the truth so its shading reads,
# red where it is far), shared with the page's legend
COLORMAP = ["#dde8f4", "#8fbde6", "#f2d060", "#ec8034", "#c0282d"]


@dataclass
class ViewPanels:
    """One view's pictures (data URIs, in display order) and figures."""

    index: int
    name: str
    pictures: list[tuple[str, str]]  # (caption, data URI)
    error: float
    error_hull: float | None = None
    iou: float | None = None


@dataclass
class ReportData:
    """Everything page.py lays out. report: report.json's dict; metrics: {"hull": {...}, "mesh":
    {...}} against the ground truth, or None; scene3d: the 3D view's JSON (meshes, cameras)."""

    out_dir: Path
    report: dict
    views: list[ViewPanels]
    scene3d: dict
    metrics: dict | None = None
    rerender_width: int = 0
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0


def write_report(out_dir: str | Path, *, capture=None, report: dict | None = None, ground_truth=None,
                 metrics: dict | None = None, rerendering=None, width: int | None = None, reporter=None) -> Path:
    """Write OUT/report.html (atomically) for the `reconstruct` output folder `out_dir`; returns its path.

    capture: the loaded capture (default: loaded from report.json's "scene"); report: report.json's
    dict (default: read from the folder); ground_truth: a trimesh or a mesh file in the capture's
    frame, or None; metrics: the result's `shape_metrics` against it when already computed;
    rerendering: the result's `render.compare.rerender` when already made (the refine stage makes
    it), else it is made `width` pixels wide (default: the refine stage's width, so a report written
    again shows the same errors; the hull is re-rendered at the same width);
    reporter: a `progress.Reporter` to say it is done.
    Raises LookingGlassError naming a missing or unreadable file.
    """
    from ..capture.scene import load_capture
    from ..metrics import load_mesh
    from ..render.compare import RERENDER_WIDTH

    start = time.perf_counter()
    out_dir = Path(out_dir)
    if report is None:
        path = out_dir / "report.json"
        if not path.exists():
            raise LookingGlassError("no report.json: not a `lookingglass reconstruct` output folder", out_dir)
        report = read_json(path, "reconstruct report")
        if not (isinstance(report, dict) and isinstance(report.get("scene"), str)):
            raise LookingGlassError("not a `lookingglass reconstruct` report (no \"scene\" entry naming the scene "
                                    "folder)", path)
    if capture is None:
        capture = load_capture(report["scene"])
    mesh = load_mesh(out_dir / "mesh.ply")
    hull = mesh if report.get("mesh_from") == "visual_hull" else load_mesh(out_dir / "visual_hull.ply")
    width = width or report.get("config", {}).get("refine", {}).get("rerender_width") or RERENDER_WIDTH
    if ground_truth is not None and not isinstance(ground_truth, trimesh.Trimesh):
        ground_truth = load_mesh(ground_truth)
    data = gather(out_dir, report, capture, mesh, hull, ground_truth, metrics, width, rerendering)
    data.seconds = time.perf_counter() - start
    from .page import render_page

    text = render_page(data)
    path = write_atomic(out_dir / REPORT_NAME, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    if reporter is not None:
        reporter.console.print(f"[green]✓[/green] {REPORT_NAME} [dim]({time.perf_counter() - start:.2f} s, "
                               f"{path.stat().st_size / 1e6:.1f} MB)[/dim]")
    return path


def gather(out_dir: Path, report: dict, capture, mesh: trimesh.Trimesh, hull: trimesh.Trimesh,
           ground_truth: trimesh.Trimesh | None, metrics: dict | None, width: int, rendered=None) -> ReportData:
    """The report's content: re-renderings, per-view pictures, metrics and the 3D scene."""
    from ..metrics import normalization_transform, shape_metrics
    from ..render.compare import RERENDER_SAMPLES, rerender

    same = hull is mesh
    # the refine stage's samples per pixel, so that the hull's error reads like the mesh's it passed
    samples = report.get("config", {}).get("refine", {}).get("rerender_samples") or RERENDER_SAMPLES
    if rendered is None or len(rendered.error) != capture.num_views:
        rendered = rerender(mesh, capture, width=width, samples_per_axis=samples)
    width = rendered.photos.shape[2]
    rendered_hull = None if same else rerender(hull, capture, width=width, samples_per_axis=samples)
    if ground_truth is not None:
        metrics = {"hull": shape_metrics(hull, ground_truth),
                   "mesh": metrics if metrics is not None else shape_metrics(mesh, ground_truth)}
    refine = next((s for s in report.get("stages", []) if s.get("name") == "refine"), {})
    ious = refine.get("silhouette_iou_after") if refine.get("kept") == "refined" else refine.get("silhouette_iou_before")
    views = view_panels(out_dir, capture, mesh, None if same else hull, ground_truth, rendered, rendered_hull, ious)
    notes: list[str] = []
    scale = normalization_transform(ground_truth)[1] if ground_truth is not None else None
    scene3d = scene_3d(capture, mesh, hull, ground_truth, scale, notes)
    return ReportData(out_dir, report, views, scene3d, metrics, rendered.photos.shape[2], notes)


# ---------------------------------------------------------------------------------------------
# Pictures
# ---------------------------------------------------------------------------------------------
def data_uri(rgb: np.ndarray, kind: str = "png") -> str:
    """(H, W, 3) display values in [0, 1] -> a PNG or JPEG data URI."""
    u8 = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)[..., ::-1]
    params = [cv2.IMWRITE_JPEG_QUALITY, 88] if kind == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 6]
    ok, buf = cv2.imencode(".jpg" if kind == "jpeg" else ".png", np.ascontiguousarray(u8), params)
    if not ok:
        raise RuntimeError(f"cannot encode a {kind} picture")
    return f"data:image/{kind};base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def crop_box(mask: np.ndarray) -> tuple[float, float, float]:
    """(centre x, centre y, half side) in pixels of `mask` (H, W): a square around the object with
    a margin (the whole frame's centre when the mask is empty)."""
    ys, xs = np.nonzero(mask)
    if not len(ys):
        h, w = mask.shape
        return w / 2, h / 2, max(h, w) / 2
    half = 0.62 * max(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1) + 4
    return (xs.min() + xs.max() + 1) / 2, (ys.min() + ys.max() + 1) / 2, half


def crop(image: np.ndarray, box: tuple[float, float, float], full_width: int, size: int = PANEL,
         fill: float = 1.0) -> np.ndarray:
    """The square `box` (in pixels of an image `full_width` wide) of `image` (H, W[, C]) of the same
    aspect at any resolution, padded with `fill` past the edges, resized to size x size float32."""
    img = np.asarray(image, np.float32)
    k = img.shape[1] / full_width
    cx, cy, half = (v * k for v in box)
    x0, x1, y0, y1 = (int(round(v)) for v in (cx - half, cx + half, cy - half, cy + half))
    h, w = img.shape[:2]
    pad = max(0, -x0, -y0, x1 - w, y1 - h)
    if pad:
        img = np.pad(img, ((pad, pad), (pad, pad)) + ((0, 0),) * (img.ndim - 2), constant_values=fill)
    part = img[y0 + pad:y1 + pad, x0 + pad:x1 + pad]
    interp = cv2.INTER_AREA if part.shape[0] > size else cv2.INTER_LINEAR
    return cv2.resize(part, (size, size), interpolation=interp)


def outlined(rgb: np.ndarray, mask: np.ndarray, colour=(1.0, 0.25, 0.05)) -> np.ndarray:
    """`rgb` with the outline of `mask` (same size, bool) drawn on it, 2 pixels wide."""
    m = mask.astype(np.uint8)
    edge = (cv2.dilate(m, np.ones((2, 2), np.uint8)) - cv2.erode(m, np.ones((2, 2), np.uint8))) > 0
    out = rgb.copy()
    out[edge] = colour
    return out


def view_panels(out_dir: Path, capture, mesh, hull, ground_truth, rendered, rendered_hull,
                ious) -> list[ViewPanels]:
    """Per view: the photo (mask outlined), the result's re-rendering (the mask outlined), then the
    normals of the hull, the network, the result and the ground truth (those that exist), each a
    square around the object. hull: None when the result is the hull."""
    import torch

    from ..render.tracer import trace_two_bounce
    from ..viz import normal_map_rgb

    V, H, W = capture.masks.shape
    maps = [out_dir / "normals" / f"view_{v:02d}.npz" for v in range(V)]
    predicted = [np.load(p) if p.exists() else None for p in maps]
    nw, nh = (predicted[0]["mask"].shape[1], predicted[0]["mask"].shape[0]) if predicted[0] is not None \
        else (rendered.masks.shape[2], rendered.masks.shape[1])
    cams = capture.cameras.with_resolution(nw, nh)
    traced = {name: trace_two_bounce(m, cams, capture.ior) for name, m in
              (("visual hull", hull if hull is not None else mesh), ("result", mesh), ("ground truth", ground_truth))
              if m is not None and not (name == "result" and hull is None)}
    factor = exposure_factor(torch.as_tensor(capture.images))
    views = []
    for v in range(V):
        box = crop_box(capture.masks[v])
        mask = crop(capture.masks[v].astype(np.float32), box, W, fill=0.0) >= 0.5
        photo = crop(linear_to_srgb(np.clip(capture.images[v] * factor, 0, 1)), box, W)
        render = crop(linear_to_srgb(rendered.renders[v]), box, W)
        pictures = [("photo, mask outlined", data_uri(outlined(photo, mask), "jpeg")),
                    ("result re-rendered", data_uri(outlined(render, mask), "jpeg"))]
        normal_pictures = [(name, tb.normal1[v].numpy(), tb.mask[v].numpy()) for name, tb in traced.items()]
        if predicted[v] is not None:
            normal_pictures.insert(1, ("network", predicted[v]["n1"], predicted[v]["mask"]))
        for name, n, m in normal_pictures:
            pictures.append((f"{name} normals", data_uri(crop(normal_map_rgb(n, m), box, W))))
        spec = getattr(capture, "spec", None)
        name = spec.views[v].image if spec is not None else f"view {v}"
        views.append(ViewPanels(v, str(name), pictures, float(rendered.error[v]),
                                float(rendered_hull.error[v]) if rendered_hull is not None else None,
                                float(ious[v]) if ious is not None and v < len(ious) else None))
    return views


# ---------------------------------------------------------------------------------------------
# The 3D view's content
# ---------------------------------------------------------------------------------------------
def display_mesh(mesh: trimesh.Trimesh, faces: int, fast: bool = False) -> trimesh.Trimesh:
    """`mesh`, decimated to about `faces` faces when it has more: by quadric edge collapse, or with
    `fast` by vertex clustering (~30x faster, coarser: for the translucent hull)."""
    if len(mesh.faces) <= faces:
        return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(mesh.vertices, np.float64),
                               face_matrix=np.asarray(mesh.faces, np.int32)))
    if fast:  # one vertex per cell; a closed surface has about twice as many faces as vertices
        cell = float(np.sqrt(2 * mesh.area / faces))
        ms.meshing_decimation_clustering(threshold=pymeshlab.PureValue(cell))
    else:
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(faces), preservenormal=True,
                                                    preservetopology=True, qualitythr=0.5)
    m = ms.current_mesh()
    return trimesh.Trimesh(m.vertex_matrix(), m.face_matrix(), process=False)


def colormap(t: np.ndarray) -> np.ndarray:
    """t in [0, 1] (N,) -> display sRGB (N, 3) along COLORMAP."""
    stops = np.array([[int(c[i:i + 2], 16) / 255 for i in (1, 3, 5)] for c in COLORMAP])
    x = np.clip(t, 0, 1) * (len(stops) - 1)
    i = np.minimum(x.astype(int), len(stops) - 2)
    f = (x - i)[:, None]
    return stops[i] * (1 - f) + stops[i + 1] * f


def nice_ceiling(x: float) -> float:
    """The smallest of 1, 2, 2.5, 5 x 10^k at least x."""
    if x <= 0:
        return 1.0
    k = 10 ** np.floor(np.log10(x))
    return float(next(m * k for m in (1, 2, 2.5, 5, 10) if m * k >= x * (1 - 1e-9)))


def glb_base64(mesh: trimesh.Trimesh) -> str:
    """Binary glTF (positions float32, indices, vertex colours when set; no normals: the page
    computes them), base64."""
    return base64.b64encode(mesh.export(file_type="glb")).decode("ascii")


def frusta(cameras, depth: float) -> list[float]:
    """Line segments (flat x, y, z pairs) drawing each camera as a pyramid `depth` deep, with a
    tick on its image's top edge so up reads."""
    o = cameras.origin.double().numpy()
    basis = cameras.basis.double().numpy()  # rows right, up, forward
    tx = cameras.tan_half_fov_x.double().numpy()
    ty = tx * cameras.height / cameras.width
    segments = []
    for v in range(len(o)):
        r, u, f = basis[v]
        corners = [o[v] + depth * (f + sx * tx[v] * r + sy * ty[v] * u) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        for k in range(4):
            segments += [o[v], corners[k], corners[k], corners[(k + 1) % 4]]
        top = o[v] + depth * (f + 1.35 * ty[v] * u)
        segments += [corners[2], top, top, corners[3]]
    return np.round(np.concatenate(segments), 5).tolist() if segments else []


def scene_3d(capture, mesh, hull, ground_truth, gt_scale: float | None, notes: list[str]) -> dict:
    """The 3D view's JSON: layers (GLB base64 and display settings), camera frusta and views."""
    layers = []
    specs = [("mesh", "result", mesh, "#8ab6e0", 1.0, True)]
    if hull is not mesh:
        specs.append(("visual_hull", "visual hull", hull, "#e0a040", 0.28, True))
    if ground_truth is not None:
        specs.append(("ground_truth", "ground truth", ground_truth, "#6cbf73", 0.45, False))
    distance = None
    for key, label, m, colour, opacity, visible in specs:
        shown = display_mesh(m, DISPLAY_FACES[key], fast=key == "visual_hull")
        if len(shown.faces) < len(m.faces):
            notes.append(f"the 3D view shows the {label} decimated from {len(m.faces)} to {len(shown.faces)} faces")
        if key == "mesh" and ground_truth is not None:
            _, d, _ = trimesh.proximity.closest_point(ground_truth, shown.vertices)
            d = np.asarray(d) / gt_scale
            top = nice_ceiling(float(np.percentile(d, 98)))
            rgb = srgb_to_linear(colormap(d / top))  # glTF vertex colours are linear
            shown.visual.vertex_colors = np.concatenate([np.round(rgb * 255), np.full((len(rgb), 1), 255)], 1).astype(np.uint8)
            distance = {"max": top, "median": float(np.median(d)), "p90": float(np.percentile(d, 90)),
                        "colors": COLORMAP}
        layers.append({"id": key, "label": label, "glb": glb_base64(shown), "color": colour, "opacity": opacity,
                       "visible": visible, "faces": int(len(shown.faces)), "faces_full": int(len(m.faces))})
    centre = (mesh.bounds[0] + mesh.bounds[1]) / 2
    radius = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]) / 2)
    cams = capture.cameras
    basis = cams.basis.double().numpy()
    origins = cams.origin.double().numpy()
    views = []
    for v in range(cams.num_views):
        reach = max(float(np.dot(centre - origins[v], basis[v, 2])), 1e-3)  # depth of the object's centre
        views.append({"origin": origins[v].round(5).tolist(),
                      "target": (origins[v] + reach * basis[v, 2]).round(5).tolist(),
                      "fov_y_deg": float(np.degrees(2 * np.arctan(float(cams.tan_half_fov_x[v]) * cams.height
                                                                  / cams.width)))})
    return {"layers": layers, "distance": distance, "frusta": frusta(cams, 0.4 * radius), "views": views,
            "center": centre.round(5).tolist(), "radius": radius}
