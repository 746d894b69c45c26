"""The `lookingglass` command line. Each command is a thin wrapper over a library function."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Optional

import typer
from rich.console import Console
from rich.markup import escape

from .errors import LookingGlassError
from .physics.constants import IOR_GLASS, PAPER_CAPTURE_FOV_X_DEG

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Reconstruct transparent objects from a few photos under a known environment map.")


SURFACE_POINTS_HELP = ("Points on the hull for the surface (SurfaceConfig.points; more keeps narrower slits "
                       "and takes longer).")
WORKERS_HELP = ("Scenes evaluated at once on the CPU, one process each (0: one per core; with a GPU, one "
                "process).")


def _surface_points(value: Optional[int]) -> Optional[int]:
    if value is not None and not 1000 <= value <= 1_000_000:
        raise LookingGlassError(f"--surface-points must be in [1000, 1000000], got {value}")
    return value


@app.command()
def reconstruct(
    scene_dir: Path = typer.Argument(..., help="Scene folder with scene.json, images, masks and envmap."),
    out: Path = typer.Option(..., "--out", help="Output folder (must be empty unless --force)."),
    preset: Optional[str] = typer.Option(None, help="Configuration preset: cpu (the default) or paper (the "
                                                    "paper's 500 + 500 latent steps, for a GPU)."),
    config: Optional[Path] = typer.Option(None, "--config", help="Re-run a saved configuration: an earlier run's "
                                                                 "report.json (or a config JSON); the options "
                                                                 "below override it."),
    hull_resolution: Optional[int] = typer.Option(None, help="Voxels along the longest side of the hull box "
                                                             "(HullConfig.resolution)."),
    surface_points: Optional[int] = typer.Option(None, help=SURFACE_POINTS_HELP),
    device: Optional[str] = typer.Option(None, help="cpu, cuda, cuda:N or auto (the default)."),
    stop_after: Optional[str] = typer.Option(None, help="Last stage to run: visual_hull, normals or surface (the "
                                                        "default)."),
    weights: Optional[Path] = typer.Option(None, help="Normal-network weights (default: the shipped ones)."),
    views: Optional[int] = typer.Option(None, help="Use the shipped weights trained for this view count (5, 10, "
                                                   "20; the nearest that ships); 0: the capture's view count."),
    force: bool = typer.Option(False, "--force", help="Overwrite a non-empty output folder."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Reconstruct the object's surface; writes mesh.ply, visual_hull.ply, points.ply, normals/ and report.json."""
    import dataclasses

    from .config import PipelineConfig, preset as make_preset
    from .pipeline import reconstruct as run
    from .progress import Reporter

    if preset is not None and config is not None:
        raise LookingGlassError("give --preset or --config, not both")
    base = PipelineConfig.from_json(config) if config is not None else make_preset(preset or "cpu")
    if hull_resolution is not None and not 16 <= hull_resolution <= 1024:
        raise LookingGlassError(f"--hull-resolution must be in [16, 1024], got {hull_resolution}")
    normals = _with_overrides(base.normals, weights=str(weights) if weights is not None else None, views=views)
    resolved = _with_overrides(base, device=device, stop_after=stop_after, normals=normals,
                               hull=_with_overrides(base.hull, resolution=hull_resolution),
                               surface=_with_overrides(base.surface, points=_surface_points(surface_points)))
    reporter = Reporter(quiet=quiet)
    report = run(scene_dir, out, dataclasses.replace(resolved), force=force, reporter=reporter)
    reporter.info(f"wrote {out / 'mesh.ply'} ({report['total_seconds']:.1f} s)")


@app.command()
def evaluate(
    pred_mesh: Path = typer.Argument(..., help="Reconstructed mesh."),
    gt_mesh: Path = typer.Argument(..., help="Ground-truth mesh."),
    samples: int = typer.Option(20000, help="Points sampled on each surface."),
    seed: int = typer.Option(0, help="Sampling seed."),
) -> None:
    """Print CD (x1e4), Metro (x1e3), CDN-mean and CDN-med (degrees) as JSON, on the unit-sphere scale of GT."""
    from .metrics import evaluate_mesh_files

    print(json.dumps(evaluate_mesh_files(pred_mesh, gt_mesh, samples=samples, seed=seed), indent=2))


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
    force: bool = typer.Option(False, "--force", help="Overwrite a non-empty output folder."),
) -> None:
    """Convert the paper's real-capture layout into a scene folder."""
    from .capture.paper_import import import_paper as run

    path = run(cams=cams, images=images, masks=masks, envmap=envmap, out=out, envmap_scale=envmap_scale,
               fov_x_deg=fov_x, size=size, force=force)
    Console(stderr=True).print(f"wrote {path}")


@app.command()
def render(
    mesh: Path = typer.Argument(..., help="Closed glass mesh (world frame)."),
    envmap: Path = typer.Option(..., "--envmap", help="Environment map (.hdr, .exr or 8-bit)."),
    out: Path = typer.Option(..., "--out", help="Scene folder to write."),
    scene: Optional[Path] = typer.Option(None, "--scene", help="Take the cameras from this scene.json."),
    rig: Optional[int] = typer.Option(None, "--rig", help="The paper's rig of 5, 10 or 20 views around the unit sphere."),
    size: Optional[tuple[int, int]] = typer.Option(None, "--size", help="Image size W H."),
    ior: float = typer.Option(IOR_GLASS, help="Index of refraction of the object."),
    seed: int = typer.Option(0, help="Seed of the rig jitter and the anti-aliasing."),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing scene folder."),
) -> None:
    """Render a glass mesh under an environment map into a scene folder (images, masks, cameras)."""
    from .capture.images import read_envmap, read_raw
    from .capture.scene import SceneSpec
    from .data.rigs import paper_rig
    from .data.synthetic import render_capture
    from .metrics import load_mesh
    from .render.tracer import RenderConfig

    if (scene is None) == (rig is None):
        raise LookingGlassError("give exactly one of --scene SCENE_JSON or --rig 5|10|20")
    glass = load_mesh(mesh)
    env = read_envmap(envmap)
    if rig is not None:
        if rig not in (5, 10, 20):
            raise LookingGlassError(f"--rig must be 5, 10 or 20, got {rig}")
        w, h = size or (480, 360)
        cameras = paper_rig(rig, seed, width=w, height=h)
    else:
        spec, _ = SceneSpec.from_json(scene)
        if size is None:
            first, _ = read_raw(Path(scene).parent / spec.views[0].image)
            size = (first.shape[1], first.shape[0])
        cameras = spec.cameras(*size)
    render_capture(glass, env, cameras, out, RenderConfig(ior=ior, seed=seed), overwrite=force)
    Console(stderr=True).print(f"wrote {out / 'scene.json'} ({cameras.num_views} views, {cameras.width}x{cameras.height})")


@app.command()
def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", help="Folder for the demo's scene, result and scores."),
    seed: int = typer.Option(1, help="Shape, environment and rig seed."),
    views: int = typer.Option(10, help="5, 10 or 20 views."),
    size: tuple[int, int] = typer.Option((240, 180), "--size", help="Image size W H."),
    force: bool = typer.Option(False, "--force", help="Overwrite a non-empty output folder."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Make a glass object, render it under a procedural environment, reconstruct and score it."""
    import numpy as np

    from .config import preset as make_preset
    from .data.envmaps import procedural_envmap
    from .data.rigs import paper_rig
    from .data.shapes import random_shape
    from .data.synthetic import render_capture
    from .fileio import write_atomic, write_json
    from .metrics import load_mesh, shape_metrics
    from .pipeline import prepare_output_dir, reconstruct as run
    from .progress import Reporter

    if views not in (5, 10, 20):
        raise LookingGlassError(f"--views must be 5, 10 or 20, got {views}")
    reporter = Reporter(quiet=quiet)
    prepare_output_dir(out, force)
    with reporter.stage("synthesize", "procedural glass shape, environment and rendered photos"):
        shape = random_shape(seed)
        write_atomic(out / "ground_truth.ply", lambda p: shape.export(p, file_type="ply"))
        env = procedural_envmap(np.random.default_rng(seed), 256)
        cameras = paper_rig(views, seed, width=size[0], height=size[1])
        render_capture(shape, env, cameras, out / "scene", overwrite=True)
    config = make_preset("cpu")
    config.device = device
    report = run(out / "scene", out / "result", config, force=True, reporter=reporter)
    mesh = load_mesh(out / "result" / "mesh.ply")
    scores = shape_metrics(mesh, shape)
    write_json(out / "scores.json", {"mesh_from": report["mesh_from"], **scores})
    from .capture.scene import load_capture
    from .viz import overview

    capture = load_capture(out / "scene")
    overview(out / "overview.png", capture.images[0], capture.masks[0], capture.cameras.select(0),
             {"ground truth": shape, "reconstruction": mesh})
    reporter.info(f"overview {out / 'overview.png'} (photo | mask | ground-truth normals | reconstructed normals)")
    reporter.info(f"mesh {out / 'result' / 'mesh.ply'} ({len(mesh.faces)} faces) vs ground truth: "
                  f"CD {scores['cd']:.2f} (x1e4), Metro {scores['metro']:.2f} (x1e3), "
                  f"CDN-mean {scores['cdn_mean']:.2f} deg, CDN-med {scores['cdn_med']:.2f} deg")


@app.command()
def generate(
    out: Path = typer.Option(..., "--out", help="Dataset folder; scenes go to OUT/SPLIT/scene_NNNNN."),
    scenes: int = typer.Option(..., "--scenes", help="Scenes in the split (indices 0 .. N-1)."),
    views: int = typer.Option(10, help="5, 10 or 20 views per scene (the paper's rigs)."),
    split: str = typer.Option("train", help="train or test (disjoint seeds and natural environment maps)."),
    seed: int = typer.Option(0, help="Dataset seed: scene i depends only on (seed, split, i)."),
    workers: int = typer.Option(0, help="Worker processes (0: one per CPU core)."),
    shard: str = typer.Option("1/1", help="K/N: make only the scenes i with i % N == K-1 (K from 1)."),
    preset: str = typer.Option("cpu", help="cpu (128x96 images, E 256x128) or paper (256x192, E 512x256)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Generate synthetic training scenes (images, masks, GT and visual-hull normals, meshes); resumable."""
    from .data.dataset import DatasetConfig, generate_dataset, parse_shard
    from .progress import Reporter

    shard_kn = parse_shard(shard)
    config = DatasetConfig.preset_named(preset)
    reporter = Reporter(quiet=quiet)
    summary = generate_dataset(out, scenes, views=views, split=split, seed=seed, config=config,
                               workers=workers, shard=shard_kn, reporter=reporter)
    made = len(summary["made"])
    rate = f", {60 * made / summary['seconds']:.1f} scenes/min" if made and summary["seconds"] > 0 else ""
    reporter.info(f"{summary['split_dir']}: made {made}, skipped {summary['skipped']} finished "
                  f"({summary['seconds']:.1f} s, {summary['workers']} worker(s){rate})")


def _device(name: str) -> str:
    """--device resolved ('auto': cuda when present); imported late, as the CLI's other modules."""
    from .config import resolve_device

    return resolve_device(name)


def _with_overrides(config: Any, **values: Any) -> Any:
    """The preset `config` with the options the user gave (None: keep the preset's value)."""
    import dataclasses

    return dataclasses.replace(config, **{k: v for k, v in values.items() if v is not None})


@app.command("train-normals")
def train_normals(
    data: Path = typer.Option(..., "--data", help="Dataset folder made by `generate` (uses DATA/train)."),
    out: Path = typer.Option(..., "--out", help="Run folder: config, checkpoints, metrics, weights."),
    views: int = typer.Option(10, help="Views per scene to train on (5, 10 or 20; a subset of the stored rig)."),
    preset: str = typer.Option("cpu", help="cpu or paper network sizes and schedule."),
    variant: str = typer.Option("wr+cv", help="basic, wr or wr+cv (the paper's ablations)."),
    epochs: Optional[int] = typer.Option(None, help="Override the preset's epochs."),
    lr: Optional[float] = typer.Option(None, help="Override the preset's initial learning rate."),
    lr_halve_epochs: Optional[int] = typer.Option(None, help="Override the preset's learning-rate halving period "
                                                             "(epochs)."),
    init: str = typer.Option("", help="Start from these weights.safetensors (fine-tuning; same network config) "
                                      "instead of a random initialization."),
    max_scenes: int = typer.Option(0, help="Use only the first N scenes (0: all)."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    seed: int = typer.Option(0, help="Initialization and shuffling seed."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Train the normal network (resumes from OUT/checkpoint.pt; runs under torchrun for DDP)."""
    from .data.torch_dataset import TransparentSceneDataset
    from .normals.train import VARIANTS, train_normals as run, train_preset
    from .progress import Reporter

    if variant not in VARIANTS:
        raise LookingGlassError(f"--variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    config = _with_overrides(train_preset(preset, views), seed=seed, max_scenes=max_scenes, epochs=epochs, lr=lr,
                             lr_halve_epochs=lr_halve_epochs, init=init)
    config.net.use_error_map, config.net.use_cost_volume = VARIANTS[variant]
    dataset = TransparentSceneDataset(data, "train", views=views, augment=True, seed=seed)
    # The network runs at the data's resolution (the dataset preset matches the network preset).
    config.net.width, config.net.height = dataset.config.width, dataset.config.height
    run(dataset, out, config, device=_device(device), reporter=Reporter(quiet=quiet))


@app.command("train-points")
def train_points(
    data: Path = typer.Option(..., "--data", help="Dataset folder made by `generate` (uses DATA/train)."),
    normals: Path = typer.Option(..., "--normals", help="The trained normal net's weights.safetensors."),
    out: Path = typer.Option(..., "--out", help="Run folder: config, feature cache, checkpoints, metrics, weights."),
    preset: str = typer.Option("cpu", help="cpu or paper network sizes and schedule."),
    loss: str = typer.Option("chamfer", help="chamfer (the paper's best), nearest or view."),
    strategy: str = typer.Option("RE", help="Feature mapping: RE (the paper's best), NE or AV."),
    epochs: Optional[int] = typer.Option(None, help="Override the preset's epochs."),
    lr: Optional[float] = typer.Option(None, help="Override the preset's initial learning rate."),
    lr_halve_epochs: Optional[int] = typer.Option(None, help="Override the preset's learning-rate halving period "
                                                             "(epochs)."),
    init: str = typer.Option("", help="Start from these weights.safetensors (fine-tuning; same network config) "
                                      "instead of a random initialization."),
    max_scenes: int = typer.Option(0, help="Use only the first N scenes (0: all)."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    seed: int = typer.Option(0, help="Initialization, shuffling and point-sampling seed."),
    threads: int = typer.Option(1, help="Torch threads on the CPU (0: half the cores; PNet is fastest on 1)."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Train the point network on normal-net features (cached in OUT/features; resumes from
    OUT/checkpoint.pt; runs under torchrun for DDP)."""
    from .data.torch_dataset import TransparentSceneDataset
    from .points.train import point_train_preset, train_points as run
    from .progress import Reporter
    from .weights import load_normal_net

    # dataclasses.replace re-runs __post_init__, which checks loss and strategy
    config = _with_overrides(point_train_preset(preset), loss=loss, strategy=strategy, seed=seed,
                             max_scenes=max_scenes, epochs=epochs, lr=lr, lr_halve_epochs=lr_halve_epochs, init=init)
    views = load_normal_net(normals).net.cfg.num_views
    dataset = TransparentSceneDataset(data, "train", views=views, augment=False)
    run(dataset, out, config, normals, device=_device(device), reporter=Reporter(quiet=quiet),
        threads=threads)


@app.command("eval-normals")
def eval_normals(
    data: Path = typer.Option(..., "--data", help="Dataset folder with a test split (DATA/test)."),
    weights: list[str] = typer.Option(..., "--weights", help="VARIANT=PATH (basic, wr, wr+cv); repeat."),
    views: int = typer.Option(10, help="Views per scene."),
    latent_iterations: int = typer.Option(10, help="Latent-optimization steps per phase for wr+cv+op (0: skip)."),
    max_scenes: int = typer.Option(0, help="Evaluate only the first N test scenes (0: all)."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    workers: int = typer.Option(0, help=WORKERS_HELP),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Print the paper's Table 1 (N1/N2 angle errors, render error) on the test split as markdown."""
    from .data.torch_dataset import TransparentSceneDataset
    from .normals.evaluate import evaluate_normals, markdown_table
    from .normals.latent import LatentOptConfig
    from .progress import Reporter

    paths = {}
    for item in weights:
        name, sep, path = item.partition("=")
        if not sep or name not in ("basic", "wr", "wr+cv"):
            raise LookingGlassError(f"--weights takes VARIANT=PATH with VARIANT basic, wr or wr+cv, got {item!r}")
        paths[name] = Path(path)
    latent = LatentOptConfig(latent_iterations, latent_iterations) if latent_iterations > 0 else None
    dataset = TransparentSceneDataset(data, "test", views=views)
    results = evaluate_normals(dataset, paths, latent, max_scenes, Reporter(quiet=quiet), _device(device), workers)
    print(markdown_table(results))


@app.command("eval-shapes")
def eval_shapes(
    data: Path = typer.Option(..., "--data", help="Dataset folder with a test split (DATA/test)."),
    weights: Optional[Path] = typer.Option(None, help="Normal-network weights (default: the shipped ones)."),
    views: int = typer.Option(10, help="Views per scene."),
    strategies: str = typer.Option("RE,NE,AV", help="Feature-mapping strategies, comma-separated."),
    latent_iterations: int = typer.Option(10, help="Latent-optimization steps per phase (0: skip)."),
    max_scenes: int = typer.Option(0, help="Evaluate only the first N test scenes (0: all)."),
    point_weights: Optional[Path] = typer.Option(None, help="PNet weights: adds a pnet row (default: shipped)."),
    surface_points: Optional[int] = typer.Option(None, help=SURFACE_POINTS_HELP),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write rows and per-scene metrics as JSON "
                                            "(after every scene; a rerun with the same settings resumes from it)."),
    device: str = typer.Option("auto", help="cpu, cuda, cuda:N or auto."),
    workers: int = typer.Option(0, help=WORKERS_HELP),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Print the paper's Table 2/3 (CD, CDN-mean, CDN-med, Metro) for the hull and the surfaces made
    from normal predictions, as markdown."""
    from .data.torch_dataset import TransparentSceneDataset
    from .fileio import write_json
    from .normals.latent import LatentOptConfig
    from .points.evaluate import evaluate_shapes, markdown_table
    from .points.features import STRATEGIES
    from .points.stage import SurfaceConfig
    from .progress import Reporter
    from .weights import shipped_weights

    chosen = tuple(s.strip().upper() for s in strategies.split(",") if s.strip())
    if not chosen or any(s not in STRATEGIES for s in chosen):
        raise LookingGlassError(f"--strategies takes a comma-separated subset of {', '.join(STRATEGIES)}, "
                                f"got {strategies!r}")
    weights = weights or shipped_weights(views)[0]
    if weights is None:
        raise LookingGlassError(f"no weights ship for {views} views; pass --weights")
    latent = LatentOptConfig(latent_iterations, latent_iterations) if latent_iterations > 0 else None
    dataset = TransparentSceneDataset(data, "test", views=views)
    point_weights = point_weights or shipped_weights(views, "points")[0]
    surface = SurfaceConfig() if _surface_points(surface_points) is None else SurfaceConfig(points=surface_points)
    settings = {"data": str(Path(data).resolve()), "weights": str(Path(weights).resolve()), "views": views,
                "surface_points": surface.points,
                "strategies": list(chosen), "latent_iterations": latent_iterations,
                "point_weights": str(Path(point_weights).resolve()) if point_weights else None}
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
    result = evaluate_shapes(dataset, weights, chosen, latent, surface, max_scenes=max_scenes, reporter=reporter,
                             point_weights=point_weights, done=done, on_scene=save, device=_device(device),
                             workers=workers)
    if save is not None:
        save(result)
    print(markdown_table(result["rows"]))


def main() -> None:
    """Entry point: user errors become one clear line on stderr and exit status 2."""
    try:
        app()
    except LookingGlassError as exc:
        Console(stderr=True, highlight=False).print(f"[red]error:[/red] {escape(str(exc))}")
        sys.exit(2)
    except KeyboardInterrupt:
        Console(stderr=True).print("interrupted")
        sys.exit(130)


if __name__ == "__main__":
    main()
