"""`eval-shapes` and `eval-normals` on a tiny generated test split: the tables, the JSON, resuming."""

import json
import math

import pytest

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.metrics import shape_metrics
from lookingglass.normals.stage import shipped_weights

from test_cli import run

pytestmark = pytest.mark.skipif(shipped_weights(10)[0] is None or shipped_weights(10, "points")[0] is None,
                                reason="no 10-view weights ship in this build")


@pytest.fixture(scope="module")
def test_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluate")
    run("generate", "--out", root, "--scenes", 1, "--split", "test", "--workers", 1, "--quiet")
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


def test_eval_shapes_scores_writes_json_and_resumes(test_split):
    out = test_split / "shapes.json"
    args = ["eval-shapes", "--data", test_split, "--latent-iterations", 0, "--strategies", "RE", "--json", out,
            "--surface-points", 8192]  # fewer than the default 40 000: faster
    first = run(*args)
    rows = table_rows(first.stdout)
    assert set(rows) == {"vh", "vh+gt-normals", "normals-RE", "pnet-RE"}
    saved = json.loads(out.read_text())
    assert [s["index"] for s in saved["scenes"]] == [0] and saved["settings"]["strategies"] == ["RE"]
    assert saved["settings"]["surface_points"] == 8192
    # the hull row is the metric of the stored hull against the stored ground truth
    gt, hull = TransparentSceneDataset(test_split, "test", views=10).meshes(0)
    assert saved["rows"]["vh"]["cd"] == pytest.approx(shape_metrics(hull, gt)["cd"], rel=1e-9)
    # ground-truth normals mapped onto the hull's points: better normals than the hull's own
    assert saved["rows"]["vh+gt-normals"]["cdn_mean"] < saved["rows"]["vh"]["cdn_mean"]
    assert all(math.isfinite(v) for r in rows.values() for v in r)

    # resuming: scene 0 (the split's only one) is read back, not redone; a marked value proves it
    marked = json.loads(out.read_text())
    marked["scenes"][0]["vh"]["cd"] = 123.0
    out.write_text(json.dumps(marked))
    second = run(*args)
    said = " ".join(second.stderr.split())  # rich wraps long lines
    assert "resuming from" in said and "1 scene(s) done" in said
    again = json.loads(out.read_text())
    assert again["scenes"] == marked["scenes"] and again["rows"]["vh"]["cd"] == 123.0
    assert table_rows(second.stdout)["vh"][0] == 123.0 and table_rows(second.stdout)["pnet-RE"] == rows["pnet-RE"]

    other = run(*args[:-6], "--strategies", "NE", "--json", out, ok=False)
    assert other.returncode == 2 and "other settings" in other.stderr and "Traceback" not in other.stderr


@pytest.fixture(scope="module")
def two_scene_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("two_scenes")
    run("generate", "--out", root, "--scenes", 2, "--split", "test", "--workers", 2, "--quiet")
    return root


def test_eval_shapes_workers_match_one_process(two_scene_split):
    """--workers 2 (a process per scene; `generate` uses the same pool) gives the records of one
    process, up to float rounding, for every scene and row."""
    records = {}
    for workers in (1, 2):
        out = two_scene_split / f"w{workers}.json"
        run("eval-shapes", "--data", two_scene_split, "--latent-iterations", 0, "--strategies", "RE", "--json", out,
            "--surface-points", 4096, "--workers", workers, "--quiet")
        records[workers] = json.loads(out.read_text())["scenes"]
    assert [s["index"] for s in records[2]] == [0, 1]
    for one, two in zip(records[1], records[2]):
        assert set(one) == set(two) == {"index", "vh", "vh+gt-normals", "normals-RE", "pnet-RE"}
        for row in ("vh", "vh+gt-normals", "normals-RE", "pnet-RE"):
            for metric, value in one[row].items():
                assert two[row][metric] == pytest.approx(value, rel=1e-3), (one["index"], row, metric)


def test_eval_normals_prints_table_1_and_workers_match_one_process(two_scene_split):
    """The table's rows and ranges; eval-normals pools every pixel of both scenes whichever process
    evaluated them, so two workers print one process's table, to its printed digits (+-1 in the last
    from float rounding)."""
    tables = {}
    for workers in (1, 2):
        proc = run("eval-normals", "--data", two_scene_split, "--weights", f"wr+cv={shipped_weights(10)[0]}",
                   "--latent-iterations", 2, "--workers", workers, "--quiet")
        tables[workers] = table_rows(proc.stdout)
    assert list(tables[2]) == list(tables[1]) == ["vh", "wr+cv", "wr+cv+op"]
    for numbers in tables[1].values():  # N1 median/mean, N2 median/mean (degrees), render error
        assert len(numbers) == 5 and all(0 < v < 90 for v in numbers[:4]) and numbers[4] > 0
    for row, numbers in tables[1].items():
        assert tables[2][row] == pytest.approx(numbers, abs=0.011), row
    bad = run("eval-normals", "--data", two_scene_split, "--weights", "cv=x.safetensors", ok=False)
    assert bad.returncode == 2 and "VARIANT=PATH" in bad.stderr


def test_surface_points_out_of_range_is_a_clear_error(test_split):
    for command in (["eval-shapes", "--data", test_split], ["reconstruct", test_split, "--out", test_split / "o"]):
        proc = run(*command, "--surface-points", 10, ok=False)
        assert proc.returncode == 2 and "--surface-points must be in" in proc.stderr and "Traceback" not in proc.stderr
