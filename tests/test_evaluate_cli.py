"""`eval-shapes` and `eval-normals` on a tiny generated test split: the tables, the JSON, resuming."""

import json
import math

import pytest
import torch

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.metrics import normal_angle_errors, shape_metrics
from lookingglass.normals.evaluate import traced_targets
from lookingglass.normals.train import normal_targets
from lookingglass.weights import shipped_weights

from cli_helpers import run, run_here

pytestmark = pytest.mark.skipif(shipped_weights(10)[0] is None or shipped_weights(10, "points")[0] is None,
                                reason="no 10-view weights ship in this build")


@pytest.fixture(scope="module")
def two_scene_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("two_scenes")
    run("generate", "--out", root, "--scenes", 2, "--split", "test", "--workers", 2, "--quiet")
    return root


def table_rows(stdout: str) -> dict[str, list[float]]:
    """{row name: its numbers} of a markdown table printed by an eval command."""
    rows = {}
    for line in stdout.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 1 and cells[0] and not cells[0].startswith("-"):
            try:
                rows[cells[0]] = [float(c) for c in cells[1:]]
            except ValueError:
                continue  # the header
    return rows


def test_eval_shapes_scores_writes_json_resumes_and_workers_agree(two_scene_split):
    """Two worker processes score both scenes; a resumed run in one process keeps the finished scene
    (marked) and redoes the other to the workers' figures up to float rounding."""
    out = two_scene_split / "shapes.json"
    args = ["eval-shapes", "--data", two_scene_split, "--latent-iterations", 0, "--strategies", "RE", "--json", out,
            "--surface-points", 4096, "--no-refine"]  # fewer points than the default 40 000: faster; the refine
    # row is tests/test_one_path.py's
    first = run(*args, "--workers", 2)
    rows = table_rows(first.stdout)
    names = {"vh", "vh+gt-normals", "normals-RE", "pnet-RE"}
    assert set(rows) == names and all(math.isfinite(v) for r in rows.values() for v in r)
    saved = json.loads(out.read_text())
    assert [s["index"] for s in saved["scenes"]] == [0, 1] and saved["settings"]["strategies"] == ["RE"]
    assert saved["settings"]["surface_points"] == 4096
    # the hull row is the metric of the stored hull against the stored ground truth
    gt, hull = TransparentSceneDataset(two_scene_split, "test", views=10).meshes(0)
    assert saved["scenes"][0]["vh"]["cd"] == pytest.approx(shape_metrics(hull, gt)["cd"], rel=1e-9)
    # ground-truth normals mapped onto the hull's points: better normals than the hull's own
    assert saved["rows"]["vh+gt-normals"]["cdn_mean"] < saved["rows"]["vh"]["cdn_mean"]

    # resuming in one process: scene 0 is read back, not redone (a marked value proves it); scene 1,
    # dropped from the file, is redone and matches what the other worker process computed
    marked = json.loads(out.read_text())
    marked["scenes"] = marked["scenes"][:1]
    marked["scenes"][0]["vh"]["cd"] = 123.0
    out.write_text(json.dumps(marked))
    second = run(*args, "--workers", 1)
    said = " ".join(second.stderr.split())  # rich wraps long lines
    assert "resuming from" in said and "1 scene(s) done" in said
    again = json.loads(out.read_text())
    assert again["scenes"][0] == marked["scenes"][0] and [s["index"] for s in again["scenes"]] == [0, 1]
    redone, by_worker = again["scenes"][1], saved["scenes"][1]
    assert set(redone) == set(by_worker) == {"index", *names}
    for row in names:
        for metric, value in by_worker[row].items():
            assert redone[row][metric] == pytest.approx(value, rel=1e-3), (row, metric)

    other = run_here(*args[:-7], "--strategies", "NE", "--json", out)
    assert other.returncode == 2 and "other settings" in other.stderr and "Traceback" not in other.stderr


def test_eval_normals_prints_table_1_and_workers_match_one_process(two_scene_split):
    """The table's rows and ranges; eval-normals pools every pixel of both scenes whichever process
    evaluated them, so two workers print one process's table, to its printed digits (+-1 in the last
    from float rounding)."""
    tables = {}
    for workers in (1, 2):
        proc = run("eval-normals", "--data", two_scene_split, "--weights", f"wr+cv={shipped_weights(10)[0]}",
                   "--latent-iterations", 2, "--workers", workers, "--quiet",
                   "--json", two_scene_split / f"normals{workers}.json")
        tables[workers] = table_rows(proc.stdout)
    # the JSON: the printed rows, and each scene's own (by index, with its IoR); the pooled median
    # lies between the two scenes' medians
    saved = json.loads((two_scene_split / "normals2.json").read_text())
    assert [s["index"] for s in saved["scenes"]] == [0, 1] and all(s["ior"] == 1.4723 for s in saved["scenes"])
    for row, numbers in saved["rows"].items():
        assert round(numbers["n1_median"], 2) == tables[2][row][0]
        per_scene = [s["rows"][row]["n1_median"] for s in saved["scenes"]]
        assert min(per_scene) <= numbers["n1_median"] <= max(per_scene), (row, per_scene)
    assert list(tables[2]) == list(tables[1]) == ["vh", "wr+cv", "wr+cv+op", "wr+cv+mv", "gt"]
    for row, numbers in tables[1].items():
        assert tables[2][row] == pytest.approx(numbers, abs=0.011), row
    truth = tables[1].pop("gt")  # the ground truth: no angle error; renders closer than the hull
    assert truth[:4] == [0.0] * 4 and 0 < truth[4] < tables[1]["vh"][4]
    for numbers in tables[1].values():  # N1 median/mean, N2 median/mean (degrees), render error
        assert len(numbers) == 5 and all(0 < v < 90 for v in numbers[:4]) and numbers[4] > 0
    bad = run_here("eval-normals", "--data", two_scene_split, "--weights", "cv=x.safetensors")
    assert bad.returncode == 2 and "VARIANT=PATH" in bad.stderr


def test_surface_points_out_of_range_is_a_clear_error(two_scene_split):
    root = two_scene_split
    for command in (["eval-shapes", "--data", root], ["reconstruct", root, "--out", root / "o"]):
        proc = run_here(*command, "--surface-points", 10)
        assert proc.returncode == 2 and "--surface-points must be in" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("command", ["eval-shapes", "eval-normals"])
def test_weights_without_their_config_fail_once_in_the_parent(two_scene_split, tmp_path, command):
    """Weights whose JSON is missing, two workers: one clear message naming the file, exit 2, no
    worker tracebacks (a pool whose initializer raises respawns its workers forever)."""
    weights = tmp_path / "copied.safetensors"
    weights.write_bytes(shipped_weights(10)[0].read_bytes())  # no copied.json beside it
    spec = str(weights) if command == "eval-shapes" else f"wr+cv={weights}"
    proc = run(command, "--data", two_scene_split, "--weights", spec, "--workers", 2, ok=False, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "copied.json" in proc.stderr and "network config not found" in proc.stderr
    assert "Traceback" not in proc.stderr


def _sha(root) -> dict:
    import hashlib
    from pathlib import Path

    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(Path(root).rglob("*")) if p.is_file()}


@pytest.mark.parametrize("command", ["eval-shapes", "eval-normals"])
def test_json_output_never_overwrites_an_input(two_scene_split, tmp_path, command):
    """--json into the dataset or onto the weights was written over them (eval-normals, exit 0)."""
    root = two_scene_split
    weights = tmp_path / "w.safetensors"
    weights.write_bytes(shipped_weights(10)[0].read_bytes())
    weights.with_suffix(".json").write_text(shipped_weights(10)[0].with_suffix(".json").read_text())
    spec = str(weights) if command == "eval-shapes" else f"wr+cv={weights}"
    before, before_w = _sha(root), _sha(tmp_path)
    for target, words in ((root / "test" / "scene_00000" / "mesh.ply", "would write into the input"),
                          (root, "is a folder"),
                          (weights, "would write into the input"), (tmp_path, "is a folder")):
        proc = run_here(command, "--data", root, "--weights", spec, "--max-scenes", 1, "--json", target)
        assert proc.returncode == 2 and words in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert _sha(root) == before and _sha(tmp_path) == before_w


def test_a_damaged_scene_is_an_error_not_a_shorter_table(two_scene_split, tmp_path):
    """A scene with a file missing was left out and the table printed over the rest, exit 0."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(two_scene_split, data)
    (data / "test" / "scene_00001" / "maps.npz").unlink()
    for command in (["eval-normals", "--weights", f"wr+cv={shipped_weights(10)[0]}"], ["eval-shapes"]):
        proc = run_here(*command, "--data", data)
        assert proc.returncode == 2 and "scene_00001" in proc.stderr and "unfinished or damaged" in proc.stderr, \
            proc.stderr
    proc = run_here("eval-shapes", "--data", two_scene_split, "--max-scenes", -1)
    assert proc.returncode == 2 and "--max-scenes must be at least 0" in proc.stderr


def test_a_truncated_scene_file_is_named(two_scene_split, tmp_path):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(two_scene_split, data)
    maps = data / "test" / "scene_00000" / "maps.npz"
    maps.write_bytes(maps.read_bytes()[:300])
    proc = run_here("eval-normals", "--weights", f"wr+cv={shipped_weights(10)[0]}", "--data", data, "--max-scenes",
                    1, "--workers", 1)
    assert proc.returncode == 2 and "maps.npz: cannot read scene maps" in proc.stderr and "Traceback" not in proc.stderr


def test_a_run_folder_inside_the_dataset_is_refused(two_scene_split):
    """A training run writes its config.json, checkpoints and weights: never into the dataset."""
    for out in (two_scene_split / "test", two_scene_split / "test" / "scene_00000", two_scene_split):
        proc = run_here("train-normals", "--data", two_scene_split, "--out", out)
        assert proc.returncode == 2 and "would write into the input" in proc.stderr, proc.stderr


def test_eval_shapes_takes_the_refine_settings(tmp_path, monkeypatch):
    """--refine.* reach the refine stage eval-shapes runs and its JSON records the whole refine config,
    so a rerun resumes only with the same settings; a bad value, or settings with --no-refine, are refused."""
    from typer.testing import CliRunner

    from lookingglass import cli
    from lookingglass.config import ConfigError
    from lookingglass.presets import preset

    seen = []
    monkeypatch.setattr("lookingglass.data.torch_dataset.TransparentSceneDataset", lambda *a, **k: "dataset")
    monkeypatch.setattr("lookingglass.points.evaluate.evaluate_shapes",
                        lambda *a, **k: seen.append(k["refine"]) or {"rows": {}, "scenes": []})
    runner = CliRunner()
    base = ["eval-shapes", "--data", "d", "--weights", "w.safetensors", "--point-weights", "p.safetensors",
            "--device", "cpu", "--quiet"]
    changed = ["--refine.fair-weight", "300", "--refine.fair-thickness", "0.1"]
    default = preset().pipeline.refine
    assert (default.fair_weight, default.fair_thickness) != (300.0, 0.1)
    for flags in (changed, []):
        out = tmp_path / f"shapes{len(flags)}.json"
        result = runner.invoke(cli.app, [*base, "--json", str(out), *flags])
        assert result.exit_code == 0, result.output
        recorded = json.loads(out.read_text())["settings"]["refine_config"]
        assert (recorded["fair_weight"], recorded["fair_thickness"]) == ((300.0, 0.1) if flags else (
            default.fair_weight, default.fair_thickness))
    assert (seen[0].fair_weight, seen[0].fair_thickness) == (300.0, 0.1)
    assert seen[1] == default
    # the JSON made with the changed settings resumes with them and is refused without them
    result = runner.invoke(cli.app, [*base, "--json", str(tmp_path / "shapes4.json"), *changed])
    assert result.exit_code == 0, result.output
    result = runner.invoke(cli.app, [*base, "--json", str(tmp_path / "shapes4.json")])
    assert result.exit_code != 0 and "other settings" in str(result.exception), result.output
    result = runner.invoke(cli.app, [*base, "--refine.fair-weight", "-1"])
    assert isinstance(result.exception, ConfigError) and "--refine.fair-weight" in str(result.exception)
    # settings for a row that is not made are refused, not ignored (even one that repeats the default);
    # --no-refine alone runs
    for flags in (changed, ["--refine.fair-weight", str(default.fair_weight)]):
        result = runner.invoke(cli.app, [*base, "--no-refine", *flags])
        assert result.exit_code != 0 and "drop --no-refine" in str(result.exception), result.output
    result = runner.invoke(cli.app, [*base, "--no-refine"])
    assert result.exit_code == 0, result.output


def test_eval_normals_scores_a_split_rendered_larger_than_the_net(tmp_path):
    """A split rendered at twice the net's size (as a capture is; the nets run at 128x96) was an
    IndexError: each row is now scored against the truth at its own size, traced from the
    ground-truth mesh, which at the stored size gives the renderer's stored maps."""
    root = tmp_path / "larger"
    run("generate", "--out", root, "--scenes", 1, "--split", "test", "--width", 256, "--height", 192,
        "--workers", 1, "--quiet")
    dataset = TransparentSceneDataset(root, "test")
    meta, stored = dataset.meta(0), normal_targets(dataset[0])
    traced = traced_targets(dataset.meshes(0)[0], dataset.capture(0).cameras, meta["ior"], meta["ext_ior"])
    assert torch.equal(traced["mask"], stored["mask"]) and torch.equal(traced["n2_valid"], stored["n2_valid"])
    for key, where in (("n1", stored["mask"]), ("n2", stored["n2_valid"])):  # float16 storage: ~0.03 degrees
        assert normal_angle_errors(traced[key], stored[key], where, channel_axis=1)["mean"] < 0.05, key
    proc = run("eval-normals", "--data", root, "--weights", f"wr+cv={shipped_weights(10)[0]}",
               "--latent-iterations", 2, "--quiet")
    rows = table_rows(proc.stdout)
    assert list(rows) == ["vh", "wr+cv", "wr+cv+op", "wr+cv+mv", "gt"]
    assert rows["gt"][:4] == [0.0] * 4 and 0 < rows["gt"][4] < rows["vh"][4]
    assert all(0 < v < 90 for numbers in (rows["vh"], rows["wr+cv"], rows["wr+cv+mv"]) for v in numbers[:4])
