"""`reconstruct` on captures with a known ground truth, scored against the visual hull.

This is how a change is judged on inputs like users' (data/validation.py makes such a set): every
scene is reconstructed by `reconstruct` itself, with the given config, and for each one the hull
and the final mesh are scored against the ground truth (CD, Metro, CDN-mean, CDN-med) and against
the photos (the re-rendering error, `render.compare`: each mesh rendered as glass from the
capture's cameras), and the
normal stage's maps against the ground truth's two-bounce normals (N1 over the object, N2 where
the true path has exactly two interfaces) beside the hull's own, with both render errors. A
network earns its place where its figure is below the hull's.

OUT/<name>/ holds each scene's `reconstruct` output (a finished one is reused when its config is
the same, so an interrupted run resumes); OUT/validation.json the records and family means.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from .capture.scene import load_capture
from .config import PipelineConfig, config_to_dict
from .errors import LookingGlassError
from .fileio import sha256_file, write_json
from .metrics import load_mesh, normal_angle_errors, shape_metrics
from .parallel import run_and_collect
from .pipeline import reconstruct
from .progress import Reporter
from .render.compare import RERENDER_SAMPLES, RERENDER_WIDTH, photos_at, rerender
from .render.tracer import trace_two_bounce
from .weights import WEIGHTS_DIR

SHAPE_METRICS = ("cd", "metro", "cdn_mean", "cdn_med", "rerender")


def normal_errors(result_dir: Path, capture, gt, hull, mesh=None) -> dict:
    """Median angle errors of the hull's and the predicted N1 and N2 against the ground truth's,
    at the network's resolution (OUT/normals/view_XX.npz), and the two render errors; with MESH
    (the final mesh), its own traced N1 and N2 too: the normals a user gets, where the prediction
    is what the normal net made of the hull. All over the same pixels (the network's mask and the
    truth's): a pixel a mesh misses counts as a 90-degree error."""
    views = sorted((result_dir / "normals").glob("view_*.npz"))
    if not views:
        return {}
    maps = []
    for path in views:
        with np.load(path) as z:
            maps.append({k: z[k] for k in ("n1", "n2", "mask")})
    H, W = maps[0]["mask"].shape
    cams = capture.cameras.with_resolution(W, H)
    truth, ours = trace_two_bounce(gt, cams, ior=capture.ior), trace_two_bounce(hull, cams, ior=capture.ior)
    mask = torch.as_tensor(np.stack([m["mask"] for m in maps])) & truth.mask
    two = mask & truth.valid
    out = {}
    found = [("hull", ours.normal1, ours.normal2),
             ("pred", np.stack([m["n1"] for m in maps]), np.stack([m["n2"] for m in maps]))]
    if mesh is not None:
        final = trace_two_bounce(mesh, cams, ior=capture.ior)
        found.append(("mesh", final.normal1, final.normal2))
    for name, n1, n2 in found:
        out[f"n1_median_{name}"] = normal_angle_errors(n1, truth.normal1, mask)["median"]
        out[f"n2_median_{name}"] = normal_angle_errors(n2, truth.normal2, two)["median"]
    report = json.loads((result_dir / "report.json").read_text())
    stage = next((s for s in report["stages"] if s["name"] == "normals"), {})
    out["render_error_hull"], out["render_error_pred"] = stage.get("render_error_vh"), stage.get("render_error")
    return out


def _weights_fingerprint(config: PipelineConfig) -> dict:
    """SHA-256 of every weights file the config may load (the shipped ones and any it names), so a
    reconstruction made with other weights is not reused."""
    files = sorted(WEIGHTS_DIR.glob("*.safetensors"))
    files += [Path(p) for p in (config.normals.weights, config.surface.point_weights) if p]
    return {str(p): sha256_file(p) for p in files if p.is_file()}


def _reconstructed(scene: Path, out: Path, config: PipelineConfig, reporter: Reporter) -> None:
    """Run `reconstruct` into OUT unless a finished run with the same config and weights is there."""
    key = {"config": config_to_dict(config), "weights": _weights_fingerprint(config)}
    stamp = out / "validate_key.json"
    try:
        if (out / "mesh.ply").exists() and json.loads(stamp.read_text()) == json.loads(json.dumps(key)):
            return
    except (OSError, ValueError):
        pass
    truth = scene.parent / "ground_truth.ply"  # shown and scored in the run's report.html
    reconstruct(scene, out, config, force=True, reporter=reporter,
                ground_truth=load_mesh(truth) if truth.exists() else None)
    write_json(stamp, key)


def evaluate_validation_set(root, out, config: PipelineConfig | None = None, names: list[str] | None = None,
                            reporter: Reporter | None = None) -> dict:
    """Reconstruct and score every scene of ROOT (data/validation.py's layout: ROOT/index.json,
    ROOT/<name>/scene/, ROOT/<name>/ground_truth.ply); returns and writes OUT/validation.json:
    {"scenes": [{"name", "family", "hull": metrics, "mesh": metrics, "mesh_from", normal errors}],
    "families": {family: means}}; when the refine stage ran, a scene's record also holds "surface"
    (its input, OUT/<name>/surface.ply, scored) and "refine" (which mesh it kept, the kept mesh's
    worst silhouette IoU, seconds)."""
    root, out = Path(root), Path(out)
    reporter = reporter or Reporter(quiet=True)
    try:
        index = json.loads((root / "index.json").read_text())
        index["shapes"].items()
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise LookingGlassError(f"not a validation set ({exc}); make one with generate-validation",
                                root / "index.json") from None
    names = names or list(index["shapes"])
    config = config or PipelineConfig(device="cpu")
    config = config.resolved()  # as reconstruct saves it, so a finished run is recognized
    records = []
    for name in reporter.track(names, description="validation scenes"):
        scene = root / name / "scene"
        run_and_collect(lambda folder: _reconstructed(folder, out / name, config, Reporter(quiet=True)), scene)
        gt = load_mesh(root / name / "ground_truth.ply")
        hull, mesh = load_mesh(out / name / "visual_hull.ply"), load_mesh(out / name / "mesh.ply")
        report = json.loads((out / name / "report.json").read_text())
        record = {"name": name, "family": index["shapes"].get(name, "?"), "mesh_from": report["mesh_from"],
                  "hull": shape_metrics(hull, gt), "mesh": shape_metrics(mesh, gt),
                  "seconds": report["total_seconds"]}
        if (out / name / "surface.ply").exists():  # the refine stage ran: its input scored too
            record["surface"] = shape_metrics(load_mesh(out / name / "surface.ply"), gt)
        refine = next((s for s in report["stages"] if s["name"] == "refine"), None)
        if refine is not None:
            chosen = "silhouette_iou_after" if refine["kept"] == "refined" else "silhouette_iou_before"
            record["refine"] = {"kept": refine["kept"], "iou_min": min(refine[chosen]),
                                "iou_min_surface": min(refine["silhouette_iou_before"]), "seconds": refine["seconds"]}
        capture = load_capture(scene)
        if "ior_estimate" in report:  # --ior auto: the estimate beside scene.json's IoR, the truth
            found = report["ior_estimate"]
            record["ior"] = {"true": float(capture.ior), "estimate": found["value"],
                             "uncertainty": found["uncertainty"], "reliable": found["reliable"],
                             "method": found.get("method", "photometric"), "contrast": found["contrast"],
                             "seconds": found["seconds"],
                             **({"learned": found["learned"]["value"]} if "learned" in found else {})}
        with torch.inference_mode():
            # a run stopped before the surface gives the hull as its mesh: its normals are the hull's, not traced again
            mesh_is_hull = report["mesh_from"] == "visual_hull"
            record.update(normal_errors(out / name, capture, gt, hull, None if mesh_is_hull else mesh))
            if mesh_is_hull and "n1_median_hull" in record:
                record.update(n1_median_mesh=record["n1_median_hull"], n2_median_mesh=record["n2_median_hull"])
        # how well each mesh explains the photos (render/compare.py); the refine stage has already
        # re-rendered its input (the surface, or the surface cut to the hull: its input carve) and its
        # result, at the same seed (and, by default, width and samples)
        views = (refine or {}).get("rerender_error_views")
        prepared = photos_at(capture, RERENDER_WIDTH)
        if views is not None and (config.refine.rerender_width, config.refine.rerender_samples) == (
                RERENDER_WIDTH, RERENDER_SAMPLES):
            input_carved = bool(refine.get("input_carve", {}).get("kept"))
            record["surface"]["rerender"] = (rerender(load_mesh(out / name / "surface.ply"), capture,
                                                      prepared=prepared).mean_error if input_carved
                                             else float(np.mean(views["input"])))
            record["mesh"]["rerender"] = float(np.mean(views["refined" if refine["kept"] == "refined" else "input"]))
        else:
            for kind in ("surface", "mesh") if "surface" in record else ("mesh",):
                record[kind]["rerender"] = rerender(load_mesh(out / name / f"{kind}.ply"), capture,
                                                    prepared=prepared).mean_error
        record["hull"]["rerender"] = rerender(hull, capture, prepared=prepared).mean_error
        records.append(record)
    result = {"config": config_to_dict(config), "scenes": records, "families": family_means(records)}
    write_json(out / "validation.json", result)
    return result


def family_means(records: list[dict]) -> dict:
    """Per family (and "all"): mean of every figure over its scenes, and the share of scenes whose
    mesh has a lower CD than its hull."""
    groups: dict[str, list[dict]] = {}
    for r in records:
        groups.setdefault(r["family"], []).append(r)
    groups["all"] = records
    means = {}
    for family, rs in groups.items():
        kinds = ("hull", "surface", "mesh") if all("surface" in r for r in rs) else ("hull", "mesh")
        row = {f"{k}_{m}": float(np.mean([r[k][m] for r in rs])) for k in kinds for m in SHAPE_METRICS}
        for key in ("n1_median_hull", "n1_median_pred", "n1_median_mesh", "n2_median_hull", "n2_median_pred",
                    "n2_median_mesh", "render_error_hull", "render_error_pred"):
            values = [r[key] for r in rs if r.get(key) is not None]
            if values:
                row[key] = float(np.mean(values))
        row["mesh_better_cd"] = sum(r["mesh"]["cd"] < r["hull"]["cd"] for r in rs) / len(rs)
        if all("refine" in r for r in rs):
            row["refine_iou_min"] = float(min(r["refine"]["iou_min"] for r in rs))
            row["refine_kept"] = sum(r["refine"]["kept"] == "refined" for r in rs) / len(rs)
        row["scenes"] = len(rs)
        means[family] = row
    return means


def markdown_table(result: dict) -> str:
    """One row per scene and per family: the hull's figure, the result's, and their ratio."""
    def pair(h, m):
        return f"{h:.2f} / {m:.2f} ({m / h:.2f}x)" if h and m is not None else ""

    def normals(row: dict, which: str) -> str:  # hull / prediction / final mesh ("-": not measured)
        hull, *rest = (row.get(f"{which}_median_{k}") for k in ("hull", "pred", "mesh"))
        if not hull:
            return ""
        return f"{hull:.2f} / " + " / ".join("-" if m is None else f"{m:.2f} ({m / hull:.2f}x)" for m in rest)

    lines = ["| scene | family | CD hull / mesh | CDN-mean hull / mesh | Metro hull / mesh | N1 median hull / pred / "
             "mesh | N2 median hull / pred / mesh |", "|---|---|---|---|---|---|---|"]
    rows = [(r["name"], r["family"], r["hull"]["cd"], r["mesh"]["cd"], r["hull"]["cdn_mean"], r["mesh"]["cdn_mean"],
             r["hull"]["metro"], r["mesh"]["metro"], r) for r in result["scenes"]]
    rows += [(f"**{f}**", f"{m['scenes']} scenes", m["hull_cd"], m["mesh_cd"], m["hull_cdn_mean"], m["mesh_cdn_mean"],
              m["hull_metro"], m["mesh_metro"], m) for f, m in result["families"].items()]
    for name, family, *v, row in rows:
        lines.append(f"| {name} | {family} | {pair(v[0], v[1])} | {pair(v[2], v[3])} | {pair(v[4], v[5])} | "
                     f"{normals(row, 'n1')} | {normals(row, 'n2')} |")
    if all("surface" in r for r in result["scenes"]) and result["scenes"]:
        lines += ["", "| scene | CD hull / surface / refined | CDN-mean hull / surface / refined | re-rendering error "
                  "hull / surface / refined | worst IoU surface / kept | kept |", "|---|---|---|---|---|---|"]

        def three(values: list[float], m: str) -> str:
            return " / ".join(f"{x:.{3 if m == 'rerender' else 2}f}" for x in values)

        kinds = ("hull", "surface", "mesh")
        for r in result["scenes"]:
            ref = r.get("refine", {})
            cells = " | ".join(three([r[k][m] for k in kinds], m) for m in ("cd", "cdn_mean", "rerender"))
            lines.append(f"| {r['name']} | {cells} | {ref.get('iou_min_surface', float('nan')):.4f} / "
                         f"{ref.get('iou_min', float('nan')):.4f} | {ref.get('kept', '')} |")
        m_all = result["families"]["all"]
        cells = " | ".join(three([m_all[f"{k}_{m}"] for k in kinds], m) for m in ("cd", "cdn_mean", "rerender"))
        lines.append(f"| **all** | {cells} | | |")
    estimated = [r for r in result["scenes"] if "ior" in r]
    if estimated:
        lines += ["", "| scene | IoR true | estimate | error | contrast | reliable |", "|---|---|---|---|---|---|"]
        for r in estimated:
            e = r["ior"]
            lines.append(f"| {r['name']} | {e['true']:.4f} | {e['estimate']:.4f} +- {e['uncertainty']:.4f} | "
                         f"{e['estimate'] - e['true']:+.4f} | {e['contrast']:.3f} | {'yes' if e['reliable'] else 'no'} |")
        for label, rs in (("all", estimated), ("reliable", [r for r in estimated if r["ior"]["reliable"]])):
            if rs:
                err = np.abs([r["ior"]["estimate"] - r["ior"]["true"] for r in rs])
                lines.append(f"| **{label}** | {len(rs)} scenes | median abs error {np.median(err):.4f} | within 0.03: "
                             f"{int((err <= 0.03).sum())} of {len(rs)} | | |")
    return "\n".join(lines)
