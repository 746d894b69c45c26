"""The validation set of non-procedural shapes and `reconstruct` scored on it against the hull."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lookingglass.capture.scene import load_capture
from lookingglass.config import PipelineConfig
from lookingglass.data.validation import EDGE, SHAPES, generate_validation_set, validation_shape
from lookingglass.errors import LookingGlassError
from lookingglass.metrics import load_mesh, shape_metrics
from lookingglass.normals.latent import LatentOptConfig
from lookingglass.normals.stage import NormalStageConfig
from lookingglass.validate import evaluate_validation_set, markdown_table, normal_errors
from lookingglass.weights import shipped_weights

GENUS = {"bracket": 1, "nut": 1, "mug": 1, "key": 1}  # the others are genus 0


@pytest.mark.parametrize("name", list(SHAPES))
def test_shapes_are_closed_unit_solids_of_their_topology(name):
    mesh = validation_shape(name)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert np.linalg.norm(mesh.vertices, axis=1).max() == pytest.approx(1.0, abs=1e-9)
    assert round(mesh.body_count - mesh.euler_number / 2) == GENUS.get(name, 0)
    assert mesh.edges_unique_length.max() <= EDGE * (1 + 1e-9)


def test_cad_faces_are_flat():
    """The nut's six sides and two rims are planes: most of its area faces one of 8 directions
    (the smooth-shaded bevels and the hole's wall take the rest)."""
    mesh = validation_shape("nut")
    normals, area = mesh.face_normals, mesh.area_faces
    # cluster by direction: the area within 1 degree of the 8 most common face normals
    keys, inverse = np.unique(np.round(normals, 3), axis=0, return_inverse=True)
    top = np.sort(np.bincount(inverse.ravel(), weights=area))[::-1][:8].sum()
    assert top / area.sum() > 0.6


def test_unknown_shape_is_refused():
    with pytest.raises(LookingGlassError, match="unknown validation shape"):
        validation_shape("teapot")


@pytest.mark.skipif(shipped_weights(5)[0] is None, reason="no normal-network weights ship in this build")
def test_reconstruct_scored_against_the_hull(tmp_path):
    """One small scene: the scores are the metrics of reconstruct's own files, the normal errors
    are finite and the hull's are those of a good hull (a pebble is convex), and a second run
    reuses the finished reconstruction."""
    generate_validation_set(tmp_path / "set", names=["pebble"], views=5, size=(128, 96), samples_per_axis=1)
    # the network's normals without the latent optimization (tests/test_latent.py's): faster
    config = PipelineConfig(device="cpu", stop_after="normals",
                            normals=NormalStageConfig(latent=LatentOptConfig(iterations_n2=0, iterations_both=0)))
    result = evaluate_validation_set(tmp_path / "set", tmp_path / "out", config)
    (record,) = result["scenes"]
    gt = load_mesh(tmp_path / "set" / "pebble" / "ground_truth.ply")
    hull = shape_metrics(load_mesh(tmp_path / "out" / "pebble" / "visual_hull.ply"), gt)
    assert record["hull"]["cd"] == pytest.approx(hull["cd"], rel=1e-9) and record["mesh_from"] == "visual_hull"
    assert 0 < record["n1_median_hull"] < 20 and 0 < record["n1_median_pred"] < 45
    # the final mesh's own normals: here (stopped after the normals) the mesh is the hull, its figures the hull's
    # (taken over, not traced a second time)
    for which in ("n1", "n2"):
        assert record[f"{which}_median_mesh"] == record[f"{which}_median_hull"]
    # and it is the mesh given that is traced: the ground truth as the mesh scores ~0
    capture = load_capture(tmp_path / "set" / "pebble" / "scene")
    hull_mesh = load_mesh(tmp_path / "out" / "pebble" / "visual_hull.ply")
    with torch.inference_mode():
        exact = normal_errors(tmp_path / "out" / "pebble", capture, gt, hull_mesh, mesh=gt)
    assert exact["n1_median_mesh"] < 0.05 and exact["n2_median_mesh"] < 0.05 and exact["n1_median_hull"] > 1
    assert record["render_error_hull"] > 0 and record["render_error_pred"] > 0
    assert result["families"]["blob"]["scenes"] == 1 and "pebble" in markdown_table(result)
    row = next(line for line in markdown_table(result).splitlines() if line.startswith("| pebble |"))
    assert row.split(" | ")[5].count("/") == 2  # N1: hull / prediction / mesh
    page = (tmp_path / "out" / "pebble" / "report.html").read_text()  # with its ground truth
    assert "ground truth normals" in page and "network normals" in page and "CDN-mean" in page
    saved = json.loads((tmp_path / "out" / "validation.json").read_text())
    assert saved["scenes"][0]["hull"] == record["hull"]
    stamp = (tmp_path / "out" / "pebble" / "report.json").stat().st_mtime_ns
    evaluate_validation_set(tmp_path / "set", tmp_path / "out", config)
    assert (tmp_path / "out" / "pebble" / "report.json").stat().st_mtime_ns == stamp


def test_variable_ior_set_and_its_estimates(tmp_path):
    """generate-validation --ior-range: each shape its own seeded IoR in the range, written to its
    scene.json and the same in another folder; index.json records the range, and a folder made
    without one refuses it. validate with --ior auto puts each estimate beside that truth."""
    small = dict(names=["pebble"], views=5, size=(64, 48), samples_per_axis=1)
    generate_validation_set(tmp_path / "a", ior_range=(1.3, 1.7), **small)
    generate_validation_set(tmp_path / "b", ior_range=(1.3, 1.7), **small)
    iors = [json.loads((tmp_path / f / "pebble" / "scene" / "scene.json").read_text())["ior"] for f in "ab"]
    assert iors[0] == iors[1] and 1.3 <= iors[0] <= 1.7 and iors[0] != pytest.approx(1.4723, abs=1e-3)
    assert json.loads((tmp_path / "a" / "index.json").read_text())["ior_range"] == [1.3, 1.7]
    generate_validation_set(tmp_path / "c", **small)
    with pytest.raises(LookingGlassError, match="other settings"):
        generate_validation_set(tmp_path / "c", ior_range=(1.3, 1.7), **small)
    config = PipelineConfig(device="cpu", stop_after="visual_hull", ior="auto")
    result = evaluate_validation_set(tmp_path / "a", tmp_path / "out", config)
    (record,) = result["scenes"]
    assert record["ior"]["true"] == iors[0] and 1.3 <= record["ior"]["estimate"] <= 1.7
    table = markdown_table(result)
    assert "| IoR true |" in table and f"| {iors[0]:.4f} |" in table and "median abs error" in table
