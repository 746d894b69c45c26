"""The `lookingglass` command line. Each command is a thin wrapper over a library function."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape

from .cliconfig import CONFIG_VALUES, ConfigOptions, apply_config_flags, config_command
from .config import VIEW_CONSENSUS_PX
from .errors import Interrupted, LookingGlassError
from .physics.constants import IOR_GLASS, IOR_MAX, IOR_MIN, PAPER_CAPTURE_FOV_X_DEG, check_ior, check_ior_range
from .presets import DEFAULT_PRESET, PRESET_NAMES
from .progress import install_interrupt_hook

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Reconstruct transparent objects from a few photos under a known environment map.")


WORKERS_HELP = ("Scenes evaluated at once on the CPU, one process each (0: one per core; with a GPU, one "
                "process).")
IOR_HELP = f"Index of refraction of the object, from {IOR_MIN} to {IOR_MAX}."
EVAL_IOR_HELP = (f"The IoR the pipeline assumes for every test scene: scene (each scene's own) or a number from "
                 f"{IOR_MIN} to {IOR_MAX}, e.g. {IOR_GLASS}, the networks' training IoR, on a variable-IoR split (the paper's "
                 "var. IoR rows). The ground truth stays each scene's own.")
FORCE_HELP = ("Replace a non-empty output folder: whole, and only once this run has finished (until then it is "
              "written in a temporary folder beside it).")
PRESET_HELP = (f"Preset the config options start from: {', '.join(PRESET_NAMES)} (lookingglass/presets.py); "
               f"the config options' shown defaults are {DEFAULT_PRESET}'s; other presets' values, where they differ, "
               "end their help.")

# The generated config options of each command (lookingglass/cliconfig.py), with the shorter
# spellings the docs use kept as aliases.
RECONSTRUCT_OPTIONS = ConfigOptions("pipeline", exclude=frozenset({"hull.device", "seed"}), aliases={
    "hull.resolution": "--hull-resolution", "surface.points": "--surface-points", "normals.weights": "--weights",
    "normals.views": "--views"})
GENERATE_OPTIONS = ConfigOptions("dataset", exclude=frozenset({"preset", "hull.num_threads", "hull.device"}))
# width and height come from the dataset, the ablation switches from --variant
TRAIN_NORMALS_OPTIONS = ConfigOptions("normal_training", aliases={"net.num_views": "--views"}, exclude=frozenset(
    {"net.width", "net.height", "net.use_error_map", "net.use_cost_volume"}))
TRAIN_POINTS_OPTIONS = ConfigOptions("point_training")
TRAIN_IOR_OPTIONS = ConfigOptions("ior_training")
SFM_OPTIONS = ConfigOptions("capture", exclude=frozenset({"ball", "stop_after"}))
BALL_OPTIONS = ConfigOptions("capture", exclude=frozenset({"sfm", "stop_after"}))
CAPTURE_OPTIONS = ConfigOptions("capture")
EVAL_SHAPES_OPTIONS = ConfigOptions("pipeline", only=frozenset({"surface.points", "normals.consensus_px",
                                                                 "normals.mirror_average", "refine"}),
                                    aliases={"surface.points": "--surface-points"})


@app.command(cls=config_command(RECONSTRUCT_OPTIONS))
def reconstruct(
    ctx: typer.Context,
    scene_dir: Path = typer.Argument(..., help="Scene folder with scene.json, images, masks and envmap."),
    out: Path = typer.Option(..., "--out", help="Output folder (missing or empty, unless --force); it appears when "
                                                "the run has finished."),
    preset: Optional[str] = typer.Option(None, help=PRESET_HELP + " paper: the paper's 500 + 500 latent steps, "
                                                                  "for a GPU."),
    config: Optional[Path] = typer.Option(None, "--config", help="Re-run a saved configuration: an earlier run's "
                                                                 "report.json (or a config JSON); the config "
                                                                 "options given override it."),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Reconstruct the object's surface; writes mesh.ply, visual_hull.ply, points.ply, normals/ and report.json."""
    import dataclasses

    from .capture.folder import check_output_folder, scene_file_in
    from .config import PipelineConfig
    from .presets import preset as make_preset

    if preset is not None and config is not None:
        raise LookingGlassError("give --preset or --config, not both")
    base = PipelineConfig.from_json(config) if config is not None else make_preset(preset or DEFAULT_PRESET).pipeline
    resolved = apply_config_flags(ctx, base)
    scene_file_in(scene_dir)
    check_output_folder(scene_dir, out, force)
    # torch, trimesh and the networks (~4 s) only once the options and the folders have passed
    from .pipeline import reconstruct as run
    from .progress import Reporter

    reporter = Reporter(quiet=quiet)
    report = run(scene_dir, out, dataclasses.replace(resolved), force=force, reporter=reporter)
    reporter.info(f"wrote {out / 'mesh.ply'} ({report['total_seconds']:.1f} s)")
    if "ior_estimate" in report:
        found = report["ior_estimate"]
        reporter.info(f"IoR estimate: {found['value']:.3f} +- {found['uncertainty']:.3f}"
                      + (" (the IoR net's)" if found.get("method") == "learned" else "")
                      + ("" if found["reliable"] else " (not reliable: see the warning)"))


@app.command()
def evaluate(
    pred_mesh: Path = typer.Argument(..., help="Reconstructed mesh."),
    gt_mesh: Path = typer.Argument(..., help="Ground-truth mesh."),
    samples: int = typer.Option(20000, help="Points sampled on each surface."),
    seed: int = typer.Option(0, help="Sampling seed."),
    report: bool = typer.Option(True, "--report/--no-report", help="When PRED_MESH is a reconstruct output's "
                                "mesh.ply, rewrite that folder's report.html with the ground truth in it."),
) -> None:
    """Print CD (x1e4), Metro (x1e3), CDN-mean and CDN-med (degrees) as JSON, on the unit-sphere scale of GT."""
    from .metrics import MAX_SAMPLES, evaluate_mesh_files

    if not 1 <= samples <= MAX_SAMPLES:
        raise LookingGlassError(f"--samples must be from 1 to {MAX_SAMPLES:,}, got {samples}")
    print(json.dumps(evaluate_mesh_files(pred_mesh, gt_mesh, samples=samples, seed=seed), indent=2))
    if report and pred_mesh.name == "mesh.ply" and (pred_mesh.parent / "report.json").exists():
        from .report import write_report

        err = Console(stderr=True, highlight=False, soft_wrap=True)
        try:
            err.print(f"wrote {escape(str(write_report(pred_mesh.parent, ground_truth=gt_mesh)))} (with the ground truth)")
        except LookingGlassError as exc:
            err.print(f"[yellow]warning:[/yellow] report.html not rewritten: {escape(str(exc))}")


@app.command()
def view(
    out: Path = typer.Argument(..., help="A reconstruct output folder (or a report.html)."),
) -> None:
    """Open OUT/report.html in the default browser and print its path (only print it where there is no
    browser). An output folder from before reports existed gets its report.html first."""
    from .report import open_report

    path, opened = open_report(out)
    print(path)
    if not opened:
        Console(stderr=True).print("no browser to open it here: open the file above in one")


@app.command("import-paper")
def import_paper(
    cams: Path = typer.Option(..., "--cams", help="The paper's camera file (cam*.txt)."),
    images: Path = typer.Option(..., "--images", help="Folder of photos (may hold more than the masks)."),
    masks: Path = typer.Option(..., "--masks", help="Folder of masks, matched to photos by file stem."),
    envmap: Path = typer.Option(..., "--envmap", help="Environment map (.hdr, .exr or 8-bit)."),
    out: Path = typer.Option(..., "--out", help="Scene folder to write."),
    envmap_scale: float = typer.Option(1.0, help="Factor bringing the envmap into the images' units."),
    fov_x: float = typer.Option(PAPER_CAPTURE_FOV_X_DEG, "--fov-x", help="Horizontal field of view in degrees."),
    size: Optional[tuple[int, int]] = typer.Option(None, "--size", help="Resize images and masks to W H."),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
) -> None:
    """Convert the paper's real-capture layout into a scene folder."""
    from .capture.images import check_image_size
    from .capture.paper_import import import_paper as run

    if size is not None:
        size = check_image_size(size, "--size")
    path = run(cams=cams, images=images, masks=masks, envmap=envmap, out=out, envmap_scale=envmap_scale,
               fov_x_deg=fov_x, size=size, force=force)
    Console(stderr=True).print(f"wrote {path}")


def _parse_up(up: Optional[tuple[float, float, float]]):
    return None if up is None else tuple(float(v) for v in up)


@app.command("import-colmap")
def import_colmap(
    model: Path = typer.Option(..., "--model", help="COLMAP model folder (text or binary; also its model/ or "
                                                    "sparse/0/), e.g. from `lookingglass sfm`."),
    images: Path = typer.Option(..., "--images", help="Folder of photos (photos without a mask are skipped)."),
    masks: Path = typer.Option(..., "--masks", help="Folder of masks (grey, or a PNG's alpha), matched to photos "
                                                    "by file stem."),
    envmap: Path = typer.Option(..., "--envmap", help="Environment map in the model's frame (e.g. from "
                                                      "`envmap-from-ball`)."),
    out: Path = typer.Option(..., "--out", help="Scene folder to write."),
    ior: float = typer.Option(IOR_GLASS, help=IOR_HELP),
    size: Optional[tuple[int, int]] = typer.Option(None, "--size", help="Resize images and masks to W H."),
    up: Optional[tuple[float, float, float]] = typer.Option(None, "--up", help="Up direction x y z in the model's "
                                                            "frame (default: the cameras' mean up)."),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
) -> None:
    """Turn a COLMAP model, its photos, the object's masks and an environment map into a scene folder:
    photos and masks undistorted to pinhole cameras, the object centred and upright, the map rotated
    along."""
    from .capture.colmap import import_colmap as run

    path = run(model, images, masks, envmap, out, ior=ior, size=size, up=_parse_up(up), force=force)
    Console(stderr=True).print(f"wrote {path}")


def _capture_config(ctx: typer.Context):
    from .presets import preset as make_preset

    return apply_config_flags(ctx, make_preset(DEFAULT_PRESET).capture)


@app.command(cls=config_command(SFM_OPTIONS))
def sfm(
    ctx: typer.Context,
    images: list[Path] = typer.Option(..., "--images", help="Folder of photos (repeat for several folders, e.g. "
                                                            "the object's and the ball's: one model for all)."),
    out: Path = typer.Option(..., "--out", help="Folder for the COLMAP model (OUT/model), its database (kept: a "
                                                "rerun skips finished steps) and sfm.json."),
    masks: Optional[Path] = typer.Option(None, "--masks", help="Object masks (by file stem): features on the "
                                                               "object are not used."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Camera poses of every photo by structure from motion (pycolmap): one shared camera, CPU SIFT;
    unregistered photos and poses that do not fit are listed."""
    from .capture.sfm import run_sfm
    from .progress import Reporter

    record = run_sfm(images, out, masks, _capture_config(ctx).sfm, Reporter(quiet=quiet))
    Console(stderr=True).print(f"wrote {out / 'model'} ({len(record['registered'])} of {record['photos']} photos "
                               "registered)")


@app.command("envmap-from-ball", cls=config_command(BALL_OPTIONS))
def envmap_from_ball(
    ctx: typer.Context,
    model: Path = typer.Option(..., "--model", help="COLMAP model holding the ball photos (e.g. from `sfm`)."),
    images: Path = typer.Option(..., "--images", help="Folder of the mirror-ball photos."),
    out: Path = typer.Option(..., "--out", help="Environment map to write (.hdr or .exr); a preview PNG and the "
                                                "ball fit (JSON) go beside it."),
    circles: Optional[Path] = typer.Option(None, "--circles", help="The ball's circle in photos where detection "
                                                                   "fails: lines 'stem cx cy r' (pixels)."),
    size: tuple[int, int] = typer.Option((1024, 512), "--size", help="Map size W H (W = 2 H)."),
    force: bool = typer.Option(False, "--force", help="Replace existing output files."),
) -> None:
    """The environment map, in the model's frame, from photos of a mirror ball: the ball found and
    triangulated, each view unwrapped, the views merged by their median."""
    from .capture.ball import envmap_from_ball as run

    record = run(model, images, out, circles=circles, size=size, config=_capture_config(ctx).ball, force=force)
    worst = max(v["residual_px"] for v in record["views"])
    Console(stderr=True).print(f"wrote {out} (ball radius {record['radius']:.4g} model units, {len(record['views'])} "
                               f"views, worst outline misfit {worst:.2f} px)")


@app.command(cls=config_command(CAPTURE_OPTIONS))
def capture(
    ctx: typer.Context,
    photos: Path = typer.Option(..., "--photos", help="Folder of the object's photos."),
    ball: Path = typer.Option(..., "--ball", help="Folder of the mirror-ball photos (same spot, same exposure)."),
    masks: Path = typer.Option(..., "--masks", help="Folder of the object's masks (by file stem)."),
    out: Path = typer.Option(..., "--out", help="Work folder: sfm/, envmap.hdr, scene/, result/ (a rerun resumes "
                                                "after the last finished stage)."),
    circles: Optional[Path] = typer.Option(None, "--circles", help="Ball circles where detection fails ('stem cx cy "
                                                                   "r' lines)."),
    ior: float = typer.Option(IOR_GLASS, help=IOR_HELP),
    size: Optional[tuple[int, int]] = typer.Option(None, "--size", help="Resize the scene's images to W H."),
    envmap_size: tuple[int, int] = typer.Option((1024, 512), "--envmap-size", help="Environment map size W H."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """From photos, ball photos and masks to a mesh: sfm, envmap-from-ball, import-colmap and
    reconstruct, each stage skipped when its output is already there."""
    from .capture.workflow import run_capture
    from .progress import Reporter

    result = run_capture(photos, ball, masks, out, _capture_config(ctx), circles=circles, ior=ior, size=size,
                         envmap_size=envmap_size, reporter=Reporter(quiet=quiet))
    Console(stderr=True).print(f"wrote {result}")


@app.command()
def render(
    mesh: Path = typer.Argument(..., help="Closed glass mesh (world frame)."),
    envmap: Path = typer.Option(..., "--envmap", help="Environment map (.hdr, .exr or 8-bit)."),
    out: Path = typer.Option(..., "--out", help="Scene folder to write."),
    scene: Optional[Path] = typer.Option(None, "--scene", help="Take the cameras from this scene.json."),
    rig: Optional[int] = typer.Option(None, "--rig", help="The paper's rig of 5, 10 or 20 views around the unit sphere."),
    size: Optional[tuple[int, int]] = typer.Option(None, "--size", help="Image size W H."),
    ior: float = typer.Option(IOR_GLASS, help=IOR_HELP),
    seed: int = typer.Option(0, help="Seed of the rig jitter and the anti-aliasing."),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
) -> None:
    """Render a glass mesh under an environment map into a scene folder (images, masks, cameras)."""
    from .capture.images import check_image_size, read_envmap, read_raw
    from .capture.scene import SceneSpec
    from .data.rigs import paper_rig
    from .data.synthetic import render_capture
    from .fileio import check_output_dir, staged_dir
    from .meshes import check_glass_mesh
    from .metrics import load_mesh
    from .render.tracer import RenderConfig

    # every option and input first: nothing is written before all are good
    if (scene is None) == (rig is None):
        raise LookingGlassError("give exactly one of --scene SCENE_JSON or --rig 5|10|20")
    if rig is not None and rig not in (5, 10, 20):
        raise LookingGlassError(f"--rig must be 5, 10 or 20, got {rig}")
    if size is not None:
        size = check_image_size(size, "--size")
    check_ior(ior, "--ior")
    inputs = [p for p in (mesh, envmap, scene) if p is not None]
    check_output_dir(out, force, inputs)
    glass = load_mesh(mesh)
    check_glass_mesh(glass, mesh)
    env = read_envmap(envmap)
    if rig is not None:
        w, h = size or (480, 360)
        cameras = paper_rig(rig, seed, width=w, height=h)
    else:
        spec, _ = SceneSpec.from_json(scene)
        if size is None:
            first, _ = read_raw(Path(scene).parent / spec.views[0].image)
            size = (first.shape[1], first.shape[0])
        cameras = spec.cameras(*size)
    with staged_dir(out, force, doing=f"render of {mesh}", inputs=inputs) as work:
        render_capture(glass, env, cameras, work, RenderConfig(ior=ior, seed=seed), overwrite=True)
    Console(stderr=True).print(f"wrote {out / 'scene.json'} ({cameras.num_views} views, {cameras.width}x{cameras.height})")


@app.command()
def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", help="Folder for the demo's scene, result and scores."),
    seed: int = typer.Option(1, help="Shape, environment and rig seed."),
    views: int = typer.Option(10, help="5, 10 or 20 views."),
    size: tuple[int, int] = typer.Option((240, 180), "--size", help="Image size W H."),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Make a glass object, render it under a procedural environment, reconstruct and score it; writes
    OUT/result/report.html (and OUT/summary.png, its first screen, where Chromium is installed)."""
    import numpy as np

    import dataclasses

    from .data.envmaps import procedural_envmap
    from .data.rigs import paper_rig
    from .data.shapes import random_shape
    from .data.synthetic import render_capture
    import subprocess

    from .capture.images import check_image_size
    from .fileio import staged_dir, write_atomic, write_json
    from .metrics import load_mesh, shape_metrics
    from .pipeline import reconstruct as run
    from .presets import preset as make_preset
    from .progress import Reporter
    from .report.browser import find_chromium, screenshot

    if views not in (5, 10, 20):
        raise LookingGlassError(f"--views must be 5, 10 or 20, got {views}")
    if seed < 0:
        raise LookingGlassError(f"--seed must be >= 0, got {seed}")
    size = check_image_size(size, "--size")
    config = dataclasses.replace(make_preset(DEFAULT_PRESET).pipeline, device=device).resolved()
    reporter = Reporter(quiet=quiet)
    with staged_dir(out, force, doing="demo") as work:
        with reporter.stage("synthesize", "procedural glass shape, environment and rendered photos"):
            shape = random_shape(seed)
            write_atomic(work / "ground_truth.ply", lambda p: shape.export(p, file_type="ply"))
            env = procedural_envmap(np.random.default_rng(seed), 256)
            cameras = paper_rig(views, seed, width=size[0], height=size[1])
            render_capture(shape, env, cameras, work / "scene", overwrite=True)
        report = run(work / "scene", work / "result", config, force=True, reporter=reporter, ground_truth=shape)
        report["scene"] = str((out / "scene").resolve())  # where the scene will be, not the temporary folder
        write_json(work / "result" / "report.json", report)
        mesh = load_mesh(work / "result" / "mesh.ply")
        scores = shape_metrics(mesh, shape)
        write_json(work / "scores.json", {"mesh_from": report["mesh_from"], **scores})
        summary = None
        if find_chromium() is not None:  # the summary picture: the report's first screen
            try:
                summary = screenshot(work / "result" / "report.html", work / "summary.png")
            except (OSError, RuntimeError, subprocess.TimeoutExpired) as exc:
                reporter.warn(f"no summary.png: headless chromium failed ({exc})")
    if summary is not None:
        reporter.info(f"summary {out / 'summary.png'} (the report's first screen)")
    reporter.info(f"report {out / 'result' / 'report.html'} (`lookingglass view {out / 'result'}` opens it)")
    reporter.info(f"mesh {out / 'result' / 'mesh.ply'} ({len(mesh.faces)} faces) vs ground truth: "
                  f"CD {scores['cd']:.2f} (x1e4), Metro {scores['metro']:.2f} (x1e3), "
                  f"CDN-mean {scores['cdn_mean']:.2f} deg, CDN-med {scores['cdn_med']:.2f} deg")


@app.command(cls=config_command(GENERATE_OPTIONS))
def generate(
    ctx: typer.Context,
    out: Path = typer.Option(..., "--out", help="Dataset folder; scenes go to OUT/SPLIT/scene_NNNNN."),
    scenes: int = typer.Option(..., "--scenes", help="Scenes in the split (indices 0 .. N-1)."),
    views: int = typer.Option(10, help="5, 10 or 20 views per scene (the paper's rigs)."),
    split: str = typer.Option("train", help="train or test (disjoint seeds and natural environment maps)."),
    seed: int = typer.Option(0, help="Dataset seed: scene i depends only on (seed, split, i)."),
    workers: int = typer.Option(0, help="Worker processes (0: one per CPU core)."),
    shard: str = typer.Option("1/1", help="K/N: make only the scenes i with i % N == K-1 (K from 1)."),
    preset: str = typer.Option(DEFAULT_PRESET, help=PRESET_HELP),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Generate synthetic training scenes (images, masks, GT and visual-hull normals, meshes); resumable."""
    from .data.dataset import generate_dataset, parse_shard
    from .presets import preset as make_preset
    from .progress import Reporter

    shard_kn = parse_shard(shard)
    config = apply_config_flags(ctx, make_preset(preset).dataset)
    reporter = Reporter(quiet=quiet)
    summary = generate_dataset(out, scenes, views=views, split=split, seed=seed, config=config,
                               workers=workers, shard=shard_kn, reporter=reporter)
    made = len(summary["made"])
    rate = f", {60 * made / summary['seconds']:.1f} scenes/min" if made and summary["seconds"] > 0 else ""
    reporter.info(f"{summary['split_dir']}: made {made}, skipped {summary['skipped']} finished "
                  f"({summary['seconds']:.1f} s, {summary['workers']} worker(s){rate})")


def _outside_inputs(path: Optional[Path], what: str, inputs) -> None:
    """Refuse an output `path` (--json, a run folder) that is one of `inputs` (files or folders) or
    lies inside one (it would overwrite it), that holds one, or that is a folder where a file is
    written (`what` "file")."""
    from .fileio import within

    if path is None:
        return
    if what == "file" and path.is_dir():
        raise LookingGlassError("is a folder; give a file name", path)
    for p in inputs:
        if within(path, p) or within(p, path):
            raise LookingGlassError(f"would write into the input {p}; give a {what} outside it", path)


def _splits(data: Path) -> list[Path]:
    """A dataset's scene folders: a JSON or a run folder beside them in DATA/ is fine, not in them."""
    return [Path(data) / "train", Path(data) / "test"]


def _eval_counts(max_scenes: int, workers: int, latent_iterations: int) -> None:
    """An evaluation's counts: none may be negative (an empty table, or a silent 0)."""
    for option, value, zero in (("--max-scenes", max_scenes, "all"), ("--workers", workers, "one per core"),
                                ("--latent-iterations", latent_iterations, "none")):
        if value < 0:
            raise LookingGlassError(f"{option} must be at least 0 (0: {zero}), got {value}")


def _device(name: str) -> str:
    """--device resolved ('auto': cuda when present); imported late, as the CLI's other modules."""
    from .config import resolve_device

    return resolve_device(name)


@app.command("train-normals", cls=config_command(TRAIN_NORMALS_OPTIONS))
def train_normals(
    ctx: typer.Context,
    data: Path = typer.Option(..., "--data", help="Dataset folder made by `generate` (uses DATA/train)."),
    out: Path = typer.Option(..., "--out", help="Run folder: config, checkpoints, metrics, weights."),
    preset: str = typer.Option(DEFAULT_PRESET, help=PRESET_HELP),
    variant: Optional[str] = typer.Option(None, help="basic, wr or wr+cv (the paper's ablations): sets the net's "
                                                     "error-map and cost-volume switches (default: the preset's, "
                                                     "both on)."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Train the normal network (resumes from OUT/checkpoint.pt; runs under torchrun for DDP). --views
    (net.num_views) picks a subset of the stored rig's views."""
    import dataclasses

    from .normals.config import VARIANTS
    from .presets import preset as make_preset

    # the options are checked before torch loads (~3 s; `auto` devices load it), the dataset once it has
    if variant is not None and variant not in VARIANTS:
        raise LookingGlassError(f"--variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    config = apply_config_flags(ctx, make_preset(preset).normal_training)
    _outside_inputs(out, "run folder", _splits(data))
    device = _device(device)

    from .data.torch_dataset import TransparentSceneDataset
    from .normals.train import train_normals as run
    from .progress import Reporter

    dataset = TransparentSceneDataset(data, "train", views=config.net.num_views, augment=config.augment, seed=config.seed,
                                     photo_noise=config.photo_noise)
    # The network runs at the data's resolution (the dataset preset matches the network preset).
    net = dataclasses.replace(config.net, width=dataset.config.width, height=dataset.config.height)
    if variant is not None:
        net = dataclasses.replace(net, use_error_map=VARIANTS[variant][0], use_cost_volume=VARIANTS[variant][1])
    run(dataset, out, dataclasses.replace(config, net=net), device=device, reporter=Reporter(quiet=quiet))


@app.command("train-points", cls=config_command(TRAIN_POINTS_OPTIONS))
def train_points(
    ctx: typer.Context,
    data: Path = typer.Option(..., "--data", help="Dataset folder made by `generate` (uses DATA/train)."),
    normals: Path = typer.Option(..., "--normals", help="The trained normal net's weights.safetensors."),
    out: Path = typer.Option(..., "--out", help="Run folder: config, feature cache, checkpoints, metrics, weights."),
    preset: str = typer.Option(DEFAULT_PRESET, help=PRESET_HELP),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    threads: int = typer.Option(1, help="Torch threads on the CPU (0: half the cores; PNet is fastest on 1)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Train the point network on normal-net features (cached in OUT/features; resumes from
    OUT/checkpoint.pt; runs under torchrun for DDP)."""
    from .presets import preset as make_preset

    # the options are checked before torch loads (~3 s; `auto` devices load it), the dataset and the
    # normal net once it has
    if threads < 0:  # torch would read it as "leave my setting alone"
        raise LookingGlassError(f"--threads must be at least 0 (0: half the cores), got {threads}")
    config = apply_config_flags(ctx, make_preset(preset).point_training)
    _outside_inputs(out, "run folder", _splits(data))
    device = _device(device)

    from .data.torch_dataset import TransparentSceneDataset
    from .points.train import train_points as run
    from .progress import Reporter
    from .weights import load_normal_net

    net_cfg = load_normal_net(normals).net.cfg
    dataset = TransparentSceneDataset(data, "train", views=net_cfg.num_views, augment=False)
    size = (dataset.config.width, dataset.config.height)
    if size != (net_cfg.width, net_cfg.height):  # before the run folder is made
        raise LookingGlassError(f"the dataset's images are {size[0]}x{size[1]} and the normal net {normals} takes "
                                f"{net_cfg.width}x{net_cfg.height}: train on data made at the net's size", data)
    run(dataset, out, config, normals, device=device, reporter=Reporter(quiet=quiet),
        threads=threads)


@app.command("train-ior", cls=config_command(TRAIN_IOR_OPTIONS))
def train_ior(
    ctx: typer.Context,
    data: Path = typer.Option(..., "--data", help="Dataset folder made by `generate --ior-range` (uses DATA/train)."),
    out: Path = typer.Option(..., "--out", help="Run folder: config, input cache, checkpoints, metrics, weights."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Train the IoR net that `reconstruct --ior auto` reads (inputs cached in OUT/features; resumes
    from OUT/checkpoint.pt; runs under torchrun for DDP)."""
    from .presets import preset as make_preset

    # the options are checked before torch loads (~3 s; `auto` devices load it), the dataset once it has
    config = apply_config_flags(ctx, make_preset().ior_training)
    _outside_inputs(out, "run folder", _splits(data))
    device = _device(device)

    from .data.torch_dataset import TransparentSceneDataset
    from .ior_net import train_ior_net
    from .progress import Reporter

    train_ior_net(TransparentSceneDataset(data, "train"), out, config, device=device, reporter=Reporter(quiet=quiet))


@app.command("eval-normals")
def eval_normals(
    data: Path = typer.Option(..., "--data", help="Dataset folder with a test split (DATA/test)."),
    weights: list[str] = typer.Option(..., "--weights", help="VARIANT=PATH (basic, wr, wr+cv); repeat."),
    views: int = typer.Option(10, help="Views per scene."),
    latent_iterations: int = typer.Option(10, help="Latent-optimization steps per phase for wr+cv+op (0: skip)."),
    consensus_px: float = typer.Option(VIEW_CONSENSUS_PX, min=0.0, help="The views' consensus for wr+cv+mv, as "
                                       "`reconstruct`'s --normals.consensus-px (0: skip the row)."),
    mirror_average: bool = typer.Option(True, "--mirror-average/--no-mirror-average", help="wr+cv+mv averages "
                                        "with the mirror image, as `reconstruct`'s --normals.mirror-average."),
    max_scenes: int = typer.Option(0, help="Evaluate only the first N test scenes (0: all)."),
    ior: str = typer.Option("scene", "--ior", help=EVAL_IOR_HELP),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the settings, the rows and each "
                                             "scene's own rows (with its IoR) as JSON."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    workers: int = typer.Option(0, help=WORKERS_HELP),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Print the paper's Table 1 (N1/N2 angle errors, render error) on the test split as markdown."""
    from .config import LatentOptConfig
    from .data.torch_dataset import TransparentSceneDataset
    from .fileio import write_json
    from .normals.evaluate import evaluate_normals, markdown_table
    from .progress import Reporter

    device = _device(device)  # checked before any work
    held = _held_ior(ior)
    paths = {}
    for item in weights:
        name, sep, path = item.partition("=")
        if not sep or name not in ("basic", "wr", "wr+cv"):
            raise LookingGlassError(f"--weights takes VARIANT=PATH with VARIANT basic, wr or wr+cv, got {item!r}")
        paths[name] = Path(path)
    _eval_counts(max_scenes, workers, latent_iterations)
    _outside_inputs(json_out, "file", [*_splits(data), *paths.values()])
    latent = LatentOptConfig(latent_iterations, latent_iterations) if latent_iterations > 0 else None
    dataset = TransparentSceneDataset(data, "test", views=views)
    table = evaluate_normals(dataset, paths, latent, max_scenes, Reporter(quiet=quiet), device, workers, ior=held,
                             consensus_px=consensus_px, mirror_average=mirror_average)
    if json_out is not None:
        settings = {"data": str(Path(data).resolve()), "weights": {k: str(p.resolve()) for k, p in paths.items()},
                    "views": views, "latent_iterations": latent_iterations, "max_scenes": max_scenes,
                    "ior": held if held is not None else "scene", "consensus_px": consensus_px,
                    "mirror_average": mirror_average}
        write_json(json_out, {"settings": settings, "rows": table.rows, "scenes": table.scenes})
    print(markdown_table(table.rows))


def _held_ior(text: str) -> float | None:
    """An evaluation's --ior: None for "scene" (each scene's own), else the number, checked."""
    from .config import parse_ior

    ior = parse_ior(text, "--ior", choices=("scene",))  # an evaluation holds the IoR known or fixed
    return None if ior == "scene" else ior


@app.command("eval-shapes", cls=config_command(EVAL_SHAPES_OPTIONS))
def eval_shapes(
    ctx: typer.Context,
    data: Path = typer.Option(..., "--data", help="Dataset folder with a test split (DATA/test)."),
    weights: Optional[Path] = typer.Option(None, help="Normal-network weights (default: the shipped ones)."),
    views: int = typer.Option(10, help="Views per scene."),
    strategies: str = typer.Option("RE,NE,AV", help="Feature-mapping strategies, comma-separated."),
    latent_iterations: int = typer.Option(0, help="Latent-optimization steps per phase (0: none, as `reconstruct`'s "
                                                  "default)."),
    max_scenes: int = typer.Option(0, help="Evaluate only the first N test scenes (0: all)."),
    point_weights: Optional[Path] = typer.Option(None, help="PNet weights: adds a pnet row (default: shipped)."),
    refine: bool = typer.Option(True, "--refine/--no-refine", help="Add a `refined` row: the pnet surface through "
                                "reconstruct's refine stage (--refine.* sets it; its JSON records it), and score "
                                "the hull, surface and refined mesh against the photos too (re-rendering error, "
                                "silhouette IoU)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write rows and per-scene metrics as JSON "
                                            "(after every scene; a rerun with the same settings resumes from it)."),
    ior: str = typer.Option("scene", "--ior", help=EVAL_IOR_HELP),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    workers: int = typer.Option(0, help=WORKERS_HELP),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Print the paper's Table 2/3 (CD, CDN-mean, CDN-med, Metro) for the hull and the surfaces made
    from normal predictions, as markdown; with --refine (the default), also the refined mesh and
    every mesh's agreement with the photos."""
    from .config import STRATEGIES, LatentOptConfig
    from .configio import config_to_dict
    from .data.torch_dataset import TransparentSceneDataset
    from .fileio import write_json
    from .points.evaluate import evaluate_shapes, markdown_table
    from .presets import preset as make_preset
    from .progress import Reporter
    from .weights import shipped_weights

    device = _device(device)  # checked before any work
    held = _held_ior(ior)
    pipeline = apply_config_flags(ctx, make_preset().pipeline)
    surface = pipeline.surface
    chosen = tuple(s.strip().upper() for s in strategies.split(",") if s.strip())
    if not chosen or any(s not in STRATEGIES for s in chosen):
        raise LookingGlassError(f"--strategies takes a comma-separated subset of {', '.join(STRATEGIES)}, "
                                f"got {strategies!r}")
    weights = weights or shipped_weights(views)[0]
    if weights is None:
        raise LookingGlassError(f"no weights ship for {views} views; pass --weights")
    normals = dataclasses.replace(pipeline.normals, latent=LatentOptConfig(latent_iterations, latent_iterations))
    _eval_counts(max_scenes, workers, latent_iterations)
    dataset = TransparentSceneDataset(data, "test", views=views)
    point_weights = point_weights or shipped_weights(views, "points")[0]
    _outside_inputs(json_out, "file", [*_splits(data), weights, *([point_weights] if point_weights else [])])
    settings = {"data": str(Path(data).resolve()), "weights": str(Path(weights).resolve()), "views": views,
                "surface_points": surface.points,
                "strategies": list(chosen), "latent_iterations": latent_iterations,
                "point_weights": str(Path(point_weights).resolve()) if point_weights else None, "refine": refine,
                "consensus_px": normals.consensus_px, "mirror_average": normals.mirror_average,
                # only when held: the JSON of an evaluation at each scene's own IoR resumes as before
                **({"ior": held} if held is not None else {})}
    refine_flags = [k for k in ctx.meta.get(CONFIG_VALUES, {}) if k.startswith("refine.")]
    if refine_flags and not (refine and point_weights is not None):
        why, fix = (("--no-refine", "drop --no-refine") if not refine else
                    ("no point-net weights", "pass --point-weights"))
        raise LookingGlassError(f"--refine.* settings given, but no refined row is made ({why}): drop them, or {fix}")
    refine = refine and point_weights is not None
    if refine:  # the whole config: a resumed JSON made with other refine settings (or other defaults) is refused
        settings["refine_config"] = json.loads(json.dumps(config_to_dict(pipeline.refine)))
    done = []
    if json_out is not None and json_out.exists():
        try:
            earlier = json.loads(json_out.read_text())
        except (OSError, ValueError) as exc:
            raise LookingGlassError(f"{json_out}: cannot read it to resume ({exc}); remove it or pick another --json")
        if earlier.get("settings") != settings:
            raise LookingGlassError(f"{json_out} holds an evaluation with other settings; remove it or pick another "
                                    "--json")
        done = earlier.get("scenes", [])
    reporter = Reporter(quiet=quiet)
    if done:
        reporter.info(f"resuming from {json_out}: {len(done)} scene(s) done")
    save = (lambda partial: write_json(json_out, {"settings": settings, **partial})) if json_out else None
    result = evaluate_shapes(dataset, weights, chosen, normals, surface, max_scenes=max_scenes, reporter=reporter,
                             point_weights=point_weights, done=done, on_scene=save, device=device,
                             workers=workers, refine=pipeline.refine if refine else None, ior=held)
    if save is not None:
        save(result)
    print(markdown_table(result["rows"]))


@app.command("generate-validation")
def generate_validation(
    out: Path = typer.Option(..., "--out", help="Folder for the validation scenes (resumable)."),
    shapes: str = typer.Option("", help="Comma-separated shape names (default: all of "
                                        "lookingglass/data/validation.py's SHAPES)."),
    views: int = typer.Option(10, help="5, 10 or 20 views (the paper's rigs)."),
    size: tuple[int, int] = typer.Option((480, 360), "--size", help="Image size W H."),
    samples_per_axis: int = typer.Option(4, help="Anti-aliasing: s x s samples per pixel."),
    seed: int = typer.Option(0, help="Rotation, rig and rendering seed."),
    ior_range: Optional[tuple[float, float]] = typer.Option(None, "--ior-range", show_default=False,
                                                  help=f"LO HI: each shape's IoR drawn from [LO, HI] (from {IOR_MIN} "
                                                       f"to {IOR_MAX}; a set to judge `--ior auto` on); default: "
                                                       f"{IOR_GLASS} for all."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Render shapes unlike the procedural training set (CAD parts, handles, thin parts, figurines) as
    captures with their ground truth: inputs like users' to judge a change on (`validate`)."""
    from .data.validation import generate_validation_set
    from .progress import Reporter

    from .capture.images import check_image_size

    if views not in (5, 10, 20):
        raise LookingGlassError(f"--views must be 5, 10 or 20, got {views}")
    size = check_image_size(size, "--size")
    if seed < 0:
        raise LookingGlassError(f"--seed must be >= 0, got {seed}")
    if not 1 <= samples_per_axis <= 64:
        raise LookingGlassError(f"--samples-per-axis must be from 1 to 64, got {samples_per_axis}")
    if out.exists() and not out.is_dir():
        raise LookingGlassError("exists and is not a folder", out)
    names = [n.strip() for n in shapes.split(",") if n.strip()] or None
    bounds = None if ior_range is None else check_ior_range(ior_range, "--ior-range")
    path = generate_validation_set(out, names, views, size, samples_per_axis, seed, reporter=Reporter(quiet=quiet),
                                   ior_range=bounds)
    Console(stderr=True).print(f"wrote {path}")


@app.command(cls=config_command(RECONSTRUCT_OPTIONS))
def validate(
    ctx: typer.Context,
    data: Path = typer.Option(..., "--data", help="A folder made by generate-validation."),
    out: Path = typer.Option(..., "--out", help="Folder for each scene's reconstruct output and validation.json "
                                                "(a finished scene with the same config is reused)."),
    preset: Optional[str] = typer.Option(None, help=PRESET_HELP),
    shapes: str = typer.Option("", help="Comma-separated shape names (default: every scene of --data)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Run `reconstruct` on every validation scene and print, per scene and family, the hull's
    figures beside the result's (CD, CDN-mean, Metro; N1/N2 medians of the hull, the normal net's
    prediction and the final mesh) as markdown."""
    from .presets import preset as make_preset
    from .progress import Reporter
    from .validate import evaluate_validation_set, markdown_table

    config = apply_config_flags(ctx, make_preset(preset or DEFAULT_PRESET).pipeline)
    names = [n.strip() for n in shapes.split(",") if n.strip()] or None
    _outside_inputs(out, "folder", [data])
    result = evaluate_validation_set(data, out, config, names, Reporter(quiet=quiet))
    print(markdown_table(result))


def main() -> None:
    """Entry point: user errors become one clear line on stderr and exit status 2."""
    install_interrupt_hook()
    try:
        app()
    except LookingGlassError as exc:
        # soft_wrap: one line whatever the terminal's width (rich wraps at 80 columns off a tty)
        Console(stderr=True, highlight=False, soft_wrap=True).print(f"[red]error:[/red] {escape(str(exc))}")
        sys.exit(2)
    except (KeyboardInterrupt, SystemExit) as exc:
        # Ctrl-C: typer turns it into exit status 130 (SystemExit, the KeyboardInterrupt in its chain).
        # One line: what was interrupted and, from the command that knew, what it left (Interrupted).
        stop = _interrupt_of(exc)
        if stop is None:
            raise
        Console(stderr=True, highlight=False, soft_wrap=True).print(escape(str(stop) if isinstance(stop, Interrupted)
                                                                           else "interrupted"))
        sys.exit(130)


def _interrupt_of(exc: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt that `exc` is or was raised from (its cause / context chain), or None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


if __name__ == "__main__":
    main()
