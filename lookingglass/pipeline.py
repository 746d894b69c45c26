"""`reconstruct`: run the pipeline's stages on a scene folder and write the results.

Stages: visual_hull -> normals (network, + latent optimization where asked; needs weights) -> surface (hull
points with the mapped normals, moved and refined by PNet when its weights ship, screened Poisson)
-> refine (the surface's vertices moved until its silhouettes match the masks, smoothed; the
better of the surface and the refined mesh is kept). Outputs (capture frame, written atomically):
  OUT/visual_hull.ply  the carved and smoothed hull
  OUT/normals/         per-view normal maps and pictures (normals stage)
  OUT/points.ply       oriented points the surface was made from (surface stage)
  OUT/surface.ply      the surface stage's mesh (refine stage; mesh.ply is then the refined one)
  OUT/refine.png       a few views: the photo, the mask's outline over the kept mesh's silhouette, its re-rendering
  OUT/mesh.ply         the surface of the last stage that ran (the hull when only it ran)
  OUT/report.json      stages asked for and run, completed, per-stage seconds and peak memory, sizes,
                       versions, config; with --ior auto the IoR estimated from mesh.ply (ior_estimate)
  OUT/report.html      all of it for a person, one self-contained page (lookingglass/report/)
OUT appears only when the run has finished (it is written in a temporary folder beside it): a failed
or interrupted run leaves no partial result, and an earlier OUT replaced with --force stays whole
until then.
"""

from __future__ import annotations

import dataclasses
import platform
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import trimesh

from . import __version__
from .capture.folder import check_output_folder
from .capture.scene import SCENE_FILE, Capture, SceneSpec, load_capture
from .config import STAGES, PipelineConfig, config_to_dict, parse_ior
from .errors import LookingGlassError, LookingGlassWarning
from .fileio import staged_dir, write_atomic, write_json
from .hull import VisualHull, carve_visual_hull
from .ior import MIN_CONTRAST, RELIABLE_MIN_WIDTH, assumed_ior, estimate_ior
from .ior_net import LEARNED_RELIABLE_STD, learned_ior, load_ior_net
from .meshes import body_volumes
from .normals.stage import NormalStageResult, run_normal_stage, second_pass, write_normal_views
from .points.stage import surface_from_normals
from .progress import Reporter, peak_memory_mb
from .refine import RefineConfig, RefineResult, refine_surface
from .render.compare import Rerendering
from .report import write_report
from .viz import silhouette_sheet
from .weights import NormalWeights, load_normal_net, load_point_net, shipped_weights



def versions() -> dict:
    """Versions of the package and the libraries that shape its numbers."""
    import numpy
    import pymeshlab
    import skimage
    import torch

    return {"lookingglass": __version__, "python": platform.python_version(), "torch": torch.__version__,
            "numpy": numpy.__version__, "trimesh": trimesh.__version__, "scikit-image": skimage.__version__,
            "pymeshlab": getattr(pymeshlab, "__version__", "unknown")}


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> Path:
    """Binary PLY, atomically."""
    return write_atomic(path, lambda tmp: mesh.export(tmp, file_type="ply"))


def mesh_summary(mesh: trimesh.Trimesh) -> dict:
    """What report.json says of a mesh: sizes, closedness, volume, bounds, and its bodies: the
    pieces it comes in, of which `cavities` are wound inward (air pockets in the glass)."""
    bodies = body_volumes(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    return {"vertices": int(len(mesh.vertices)), "faces": int(len(mesh.faces)),
            "watertight": bool(mesh.is_watertight), "volume": float(mesh.volume) if mesh.is_watertight else None,
            "bounds": mesh.bounds.tolist(), "bodies": int(len(bodies)),
            "cavities": int((bodies < 0).sum()) if mesh.is_watertight else None}


def write_points(path: Path, points: np.ndarray, normals: np.ndarray) -> Path:
    """Binary PLY point cloud with per-point normals (x y z nx ny nz, float32), atomically.
    points, normals: (N, 3)."""
    names = ("x", "y", "z", "nx", "ny", "nz")
    records = np.empty(len(points), dtype=[(k, "<f4") for k in names])
    for i, k in enumerate("xyz"):
        records[k], records["n" + k] = points[:, i], normals[:, i]
    header = ("ply\nformat binary_little_endian 1.0\n" f"element vertex {len(points)}\n"
              + "".join(f"property float {k}\n" for k in names) + "end_header\n")
    return write_atomic(path, lambda tmp: Path(tmp).write_bytes(header.encode("ascii") + records.tobytes()))


def _given_weights(config: PipelineConfig) -> NormalWeights | None:
    """The normal net the config names, loaded (so a bad file is refused before any work, even when
    the run stops before the normals), and the point net it names checked the same way."""
    if config.surface.point_weights:
        load_point_net(config.surface.point_weights)
    return load_normal_net(config.normals.weights) if config.normals.weights else None


def _normal_weights(capture, config: PipelineConfig,
                    given: NormalWeights | None) -> tuple[NormalWeights | None, int, int]:
    """The normal net the config names (`given`, loaded) or the shipped one for the nearest view
    count, the view count it was trained for and the one asked for; checked against the capture
    before any stage runs (the net resizes the photos, so their aspect must be its own, and it
    normalizes their exposure, so they may not all be black)."""
    requested = config.normals.views or capture.num_views
    if given is not None:
        weights, trained_views = given, requested
    else:
        path, trained_views = shipped_weights(requested)
        if path is None:
            return None, 0, requested
        weights = load_normal_net(path)
    width, height = weights.net.cfg.width, weights.net.cfg.height
    if abs(capture.width / capture.height - width / height) > 0.02 * width / height:
        raise LookingGlassError(f"the photos are {capture.width}x{capture.height}, but the normal network takes "
                                f"{width}x{height} images (aspect {width / height:.3f}): crop the photos, masks and "
                                "field of view to that aspect, or stop after the visual hull", capture.root)
    if not float(capture.images.mean(dtype=np.float64)) > 0:
        raise LookingGlassError(f"every photo is black (mean radiance 0, all {capture.num_views} views): the normal "
                                "network has nothing to see; check the images' exposure and encoding, or stop after "
                                "the visual hull", capture.root / SCENE_FILE)
    return weights, trained_views, requested


def _assumed_ior(capture: Capture, config: PipelineConfig) -> tuple[Capture, str]:
    """The capture with the IoR every stage assumes (they read `capture.ior`), and where it came
    from: "scene" (scene.json's), "config" (a number in `config.ior`, e.g. `--ior 1.6`) or "auto"
    (the networks' IoR in `config.ior_range`, until the estimate after the last stage)."""
    ior = parse_ior(config.ior)
    if ior == "scene":
        return capture, "scene"
    if ior == "auto":
        return capture.with_ior(assumed_ior(config.ior_range)), "auto"
    return capture.with_ior(ior), "config"


def _estimate_ior(capture: Capture, mesh: trimesh.Trimesh, mesh_stage: str, config: PipelineConfig,
                  reporter: Reporter) -> dict:
    """`--ior auto`: the IoR at which the kept mesh best explains the photos (lookingglass/ior.py) and
    the IoR net's reading of the photos against the same mesh (lookingglass/ior_net.py, where weights
    ship; trained on hulls, it reads a better mesh better: docs/results.md). The search's value where
    it is reliable (a deep curve, its minimum inside the range, photos RELIABLE_MIN_WIDTH wide), the
    net's elsewhere, where the search runs low (docs/results.md, "Glass of unknown IoR"), unless the
    range asked for reaches beyond the net's; the other's value is kept in the report. A warning
    when the value is not to be trusted."""
    with reporter.stage("ior", "IoR estimate") as rec:
        estimate = estimate_ior(mesh, capture, config.ior_range, device=config.device)
        found = {**estimate.report(), "mesh_from": mesh_stage, "method": "photometric"}
        weights, trained_views = shipped_weights(capture.num_views, "ior")  # the nearest trained view count
        learned = None if weights is None else learned_ior(capture, mesh, load_ior_net(weights), config.ior_range,
                                                            config.device)
        if learned is not None:
            found["learned"] = {**learned.report(), "trained_views": trained_views}
            if not estimate.reliable and not learned.beyond_trained_range:
                found["photometric"] = {k: found[k] for k in ("value", "uncertainty", "reliable")}
                found.update(value=round(learned.value, 4), uncertainty=round(learned.uncertainty, 4),
                             method="learned", reliable=learned.uncertainty <= LEARNED_RELIABLE_STD)
        rec.update(found)
    if not found["reliable"]:
        why = (f"the IoR net is unsure (spread {found['uncertainty']:.3f} > {LEARNED_RELIABLE_STD})"
               if found["method"] == "learned" else
               f"its minimum is at an end of the range {config.ior_range[0]}-{config.ior_range[1]} (the IoR may lie "
               "beyond it: widen --ior-range)" if estimate.at_bound else
               f"the photos hardly tell the candidates apart (contrast {estimate.contrast:.3f} < {MIN_CONTRAST}: the "
               "mesh explains too little of the refraction)" if estimate.contrast < MIN_CONTRAST else
               f"photos {estimate.photo_width} px wide give a mesh too coarse for it (validated from "
               f"{RELIABLE_MIN_WIDTH} px; at 128 px it is ~0.09 off)")
        warnings.warn(LookingGlassWarning(
            f"IoR estimate {found['value']:.3f} +- {found['uncertainty']:.3f} is not reliable: {why}"
            + ("" if found["method"] == "learned" else "; errors in the shape bias it low")
            + ". Pass --ior if the material is known"))
    return found


def _normals(capture, hull: VisualHull, weights: NormalWeights, trained_views: int, requested: int,
             config: PipelineConfig, out_dir: Path, reporter: Reporter) -> NormalStageResult:
    """The normals stage; writes OUT/normals/."""
    latent = config.normals.latent
    title = "normals (network" + (" + latent optimization)" if latent.iterations_n2 + latent.iterations_both else ")")
    with reporter.stage("normals", title) as rec:
        result = run_normal_stage(capture, hull.mesh, weights, config.normals, config.device)
        write_normal_views(out_dir / "normals", result)
        rec.update(result.report, trained_views=trained_views)
        if trained_views != requested:
            rec["note"] = f"{requested} views: using the weights trained for {trained_views}"
    return result


def _surface(hull: VisualHull, normals: NormalStageResult, config: PipelineConfig, trained_views: int,
             device: str, out_dir: Path, reporter: Reporter) -> trimesh.Trimesh:
    """The surface stage with PNet (the config's weights, or the shipped ones for the normal net's
    view count); writes OUT/points.ply and returns the mesh."""
    path = Path(config.surface.point_weights) if config.surface.point_weights \
        else shipped_weights(trained_views, "points")[0]
    point_net = load_point_net(path) if path is not None else None
    if point_net is not None:
        point_net.net.to(device)
        if point_net.strategy != config.surface.strategy:
            reporter.warn(f"surface.strategy {config.surface.strategy} is not used: the point network maps its "
                          f"features with {point_net.strategy}, the strategy it was trained on")
    with reporter.stage("surface", "surface (feature mapping + PNet + Poisson)") as rec:
        mesh, oriented = surface_from_normals(hull, normals.maps, config.surface, point_net)
        write_points(out_dir / "points.ply", oriented.points, oriented.normals)
        if "closing" in mesh.metadata:  # Poisson's surface had handles: were the narrow ones filled, and why
            rec["tunnels_closed"] = mesh.metadata["closing"]
        rec.update(point_weights=str(path) if path is not None else None, mesh=mesh_summary(mesh),
                   points=int(len(oriented.points)), points_seen=float(oriented.seen.mean()),
                   strategy=point_net.strategy if point_net is not None else config.surface.strategy)
    return mesh


def refine_stage(capture: Capture, hull: VisualHull, surface: trimesh.Trimesh, weights: NormalWeights,
                 config: RefineConfig, device: str = "cpu") -> RefineResult:
    """The refine stage as `reconstruct` runs it, without its files: `refine_surface` against the
    capture's masks and photos, its normal term fed by the normal net's second pass (the net run
    again on the mesh the silhouette iterations leave)."""
    return refine_surface(surface, hull, capture.masks, capture.cameras, config, capture=capture,
                          normals=second_pass(capture, weights, device), view_names=capture.mask_names)


@dataclasses.dataclass
class StageMeshes:
    """What the network stages make of one capture: the normal stage's result, the PNet surface and
    the refine stage's result (None when not asked for)."""

    normals: NormalStageResult
    surface: trimesh.Trimesh
    refined: RefineResult | None


def stage_meshes(capture: Capture, hull: VisualHull, weights: NormalWeights, point_net,
                 config: PipelineConfig, refine: bool = True) -> StageMeshes:
    """The normal, surface and refine stages on `hull` as `reconstruct` runs them (the same calls,
    without its files and report), for evaluations and experiments that score what users get.
    point_net: a loaded point net (None: the surface without PNet). Raises what the stages raise (a
    failed Poisson: LookingGlassError)."""
    device = config.resolved().device
    normals = run_normal_stage(capture, hull.mesh, weights, config.normals, device)
    surface = surface_from_normals(hull, normals.maps, config.surface, point_net)[0]
    refined = refine_stage(capture, hull, surface, weights, config.refine, device) if refine else None
    return StageMeshes(normals, surface, refined)


def _refine(capture, hull: VisualHull, surface: trimesh.Trimesh, weights: NormalWeights,
            config: PipelineConfig, out_dir: Path, reporter: Reporter) -> RefineResult:
    """The refine stage: writes OUT/surface.ply (its input) and OUT/refine.png; returns its result
    (the kept mesh, its re-rendering). Its normal term runs the normal stage again, on its own mesh."""
    with reporter.stage("refine", "refine (silhouettes + smoothness + the normal net's second pass)") as rec:
        write_mesh(out_dir / "surface.ply", surface)
        result = refine_stage(capture, hull, surface, weights, config.refine, config.device)
        views = sorted(set(np.linspace(0, capture.num_views - 1, min(4, capture.num_views)).round().astype(int)))
        silhouette_sheet(out_dir / "refine.png", capture.images, capture.masks, result.casts, views,
                         result.rerendering)
        rec.update(result.report, view_coverage=[round(float(c), 4) for c in hull.view_coverage],
                   mesh=mesh_summary(result.mesh))
    return result


def _scene_files(scene_dir: Path) -> list[Path]:
    """The files scene.json names (images, masks, environment map), so that an output folder that
    holds one (`--out scene/images --force`) is refused before it replaces them; none when scene.json
    does not parse (loading the capture then says why)."""
    try:
        spec, _ = SceneSpec.from_json(scene_dir / SCENE_FILE)
    except LookingGlassError:
        return []
    return [scene_dir / spec.envmap, *(scene_dir / f for v in spec.views for f in (v.image, v.mask))]


def reconstruct(scene_dir: Path, out_dir: Path, config: PipelineConfig | None = None, force: bool = False,
                reporter: Reporter | None = None, ground_truth: trimesh.Trimesh | None = None) -> dict:
    """Reconstruct the object in the scene folder `scene_dir` into the folder `out_dir`; returns the
    report dict (also OUT/report.json).

    Everything that can be checked before work starts is (the config and its device, the weights
    files it names, that `out_dir` can be written and, unless `force`, is empty or missing); then
    the run writes into a temporary folder beside `out_dir` (`fileio.staged_dir`) that becomes
    `out_dir` only when every stage asked for has finished (with `force` the old folder is replaced
    whole at that moment). A failed or interrupted run leaves `out_dir` as it was. report.json says
    which stages were asked for and which ran, and `"completed": true`. ground_truth (capture
    frame), when known, is shown and scored in OUT/report.html.
    """
    config = config or PipelineConfig()
    config = dataclasses.replace(config)  # validated (a config edited after it was made is checked here)
    wanted = STAGES[:STAGES.index(config.stop_after) + 1]
    reporter = reporter or Reporter(quiet=True)
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    start = time.perf_counter()
    # the device is resolved once, for every stage (the hull carves where the networks run), and
    # saved resolved in report.json's config
    config = config.resolved()
    check_output_folder(scene_dir, out_dir, force)
    given = _given_weights(config)
    inputs = [scene_dir, *_scene_files(scene_dir), *(p for p in (config.normals.weights, config.surface.point_weights)
                                                     if p)]
    with staged_dir(out_dir, force, doing=f"reconstruct of {scene_dir}", inputs=inputs) as work:
        report, capture, rendered = _run(scene_dir, work, config, wanted, given, reporter)
        report["total_seconds"] = round(time.perf_counter() - start, 3)
        write_json(work / "report.json", report)
        write_report(work, capture=capture, report=report, ground_truth=ground_truth, rerendering=rendered,
                     reporter=reporter)
    return report


def _run(scene_dir: Path, out_dir: Path, config: PipelineConfig, wanted: tuple[str, ...],
         given: NormalWeights | None, reporter: Reporter) -> tuple[dict, Capture, Rerendering | None]:
    """The stages, writing into `out_dir` (the temporary folder); returns the report, the capture and
    the kept mesh's re-rendering when the refine stage made one."""
    device = config.device
    first = len(reporter.stages)  # a reporter may have timed earlier work (the demo's, other scenes')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with reporter.stage("load", f"load {scene_dir}") as rec:
            capture, ior_source = _assumed_ior(load_capture(scene_dir), config)
            rec.update(views=capture.num_views, image_size=[capture.width, capture.height])
            weights, trained_views, requested = _normal_weights(capture, config, given) if "normals" in wanted \
                else (None, 0, 0)

        with reporter.stage("visual_hull", "visual hull") as rec:
            try:
                hull = carve_visual_hull(capture.masks, capture.cameras, config.hull, view_names=capture.mask_names)
            except LookingGlassError as exc:  # about the masks and cameras together: scene.json lists both
                if exc.path is not None:
                    raise
                raise LookingGlassError(str(exc), capture.root / SCENE_FILE) from None
            write_mesh(out_dir / "visual_hull.ply", hull.mesh)
            rec.update(mesh=mesh_summary(hull.mesh), voxel_size=float(hull.voxel_size),
                       timings={k: round(float(v), 3) for k, v in hull.timings.items()})

        best, best_stage = hull.mesh, "visual_hull"
        normals = rendered = None
        if "normals" in wanted and weights is None:
            reporter.warn("no trained normal-network weights ship with this build: stopping after the visual hull")
        elif "normals" in wanted:
            normals = _normals(capture, hull, weights, trained_views, requested, config, out_dir, reporter)
        if normals is not None and "surface" in wanted:
            best = _surface(hull, normals, config, trained_views, device, out_dir, reporter)
            best_stage = "surface"
            if "refine" in wanted:
                refined = _refine(capture, hull, best, weights, config, out_dir, reporter)
                best, best_stage, rendered = refined.mesh, "refine", refined.rerendering
        write_mesh(out_dir / "mesh.ply", best)
        estimate = (_estimate_ior(capture, best, best_stage, config, reporter) if ior_source == "auto"
                    else None)
    messages = [str(w.message) for w in caught]
    for message in messages:
        reporter.warn(message)

    report = {
        "completed": True,
        "scene": str(scene_dir.resolve()),
        "num_views": capture.num_views,
        "image_size": [capture.width, capture.height],
        "ior": capture.ior,
        "ior_source": ior_source,
        **({"ior_estimate": estimate} if estimate is not None else {}),
        "device": device,
        "stages_requested": list(wanted),
        "stages_run": [s["name"] for s in reporter.stages[first:] if s["name"] in STAGES],
        "stages": reporter.stages[first:],
        "mesh_from": best_stage,
        "normalization": {"center": [float(c) for c in hull.center], "scale": float(hull.scale)},
        "warnings": messages,
        "total_seconds": None,
        "peak_memory_mb": round(peak_memory_mb(), 1),
        **({"gpu_peak_memory_mb": round(torch.cuda.max_memory_allocated(device) / 2**20, 1)}
           if device.startswith("cuda") else {}),
        "versions": versions(),
        "config": config_to_dict(config),
    }
    return report, capture, rendered
