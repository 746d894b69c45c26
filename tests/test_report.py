"""report.html: self-contained, complete, and drawn by a real browser (headless Chromium)."""

import base64
import io
import json
import os
import re
import shutil

import numpy as np
import pytest
import trimesh

from lookingglass.report import open_report
from lookingglass.report.browser import find_chromium, load_page
from lookingglass.report.build import COLORMAP, colormap, display_mesh, nice_ceiling
from lookingglass.weights import shipped_weights

from cli_helpers import run

NO_CHROMIUM = ("headless Chromium is not installed (Debian's `chromium` package; scripts/setup.sh installs it "
               "when run as root or with sudo; LOOKINGGLASS_CHROMIUM names another binary)")



@pytest.fixture(scope="module")
def small_run(torus_run, tmp_path_factory):
    """The torus capture's reconstruction (conftest.py), copied and evaluated against its ground
    truth, which rewrites the report with the ground truth in it."""
    root = tmp_path_factory.mktemp("report")
    shutil.copytree(torus_run / "out", root / "out")
    shutil.copy(torus_run / "gt.ply", root / "gt.ply")
    first = (root / "out" / "report.html").read_text()
    proc = run("evaluate", root / "out" / "mesh.ply", root / "gt.ply")
    assert "report.html" in proc.stderr and json.loads(proc.stdout)["cd"] > 0
    return root, first


def scene_data(page: str) -> dict:
    return json.loads(re.search(r'<script type="application/json" id="lg-data">(.*?)</script>', page, re.S)
                      .group(1).replace("<\\/", "</"))


def test_report_is_complete_and_self_contained(small_run):
    root, without_gt = small_run
    page = (root / "out" / "report.html").read_text()
    assert len(page.encode()) < 10e6
    # nothing to fetch: a policy forbidding every request, pictures as data URIs, no links out
    assert "default-src 'none'" in page
    assert all(uri.startswith("data:") for uri in re.findall(r'<img[^>]* src="([^"]*)"', page))
    assert not re.search(r'<(script|link|iframe)[^>]* (src|href)=', page)
    assert all(h.startswith("#") for h in re.findall(r'<a[^>]* href="([^"]*)"', page))
    data = scene_data(page)
    views = 10
    assert len(re.findall(r'<div class="view card" id="view-\d\d">', page)) == views
    assert len(data["views"]) == views and len(data["frusta"]) == views * 10 * 2 * 3  # 10 segments a camera
    layers = {layer["id"]: layer for layer in data["layers"]}
    expected = {"mesh", "ground_truth"} | ({"visual_hull"} if shipped_weights(10)[0] else set())
    assert set(layers) == expected
    result = trimesh.load(root / "out" / "mesh.ply", force="mesh")
    shown = trimesh.load(io.BytesIO(base64.b64decode(layers["mesh"]["glb"])), file_type="glb", force="mesh")
    assert len(shown.faces) == layers["mesh"]["faces"] == min(len(result.faces), layers["mesh"]["faces"])
    np.testing.assert_allclose(shown.bounds, result.bounds, atol=0.02)  # same frame, no axis swap
    assert len(np.unique(shown.visual.vertex_colors[:, :3], axis=0)) > 10  # coloured by distance to the truth
    assert data["distance"]["max"] > 0
    # the numbers: metrics against the truth, per-stage time, config; per-view pictures and errors
    for text in ("vs ground truth", "CDN-mean", "Time and memory per stage", "re-rendering error", "&quot;hull&quot;",
                 "photo, mask outlined", "result re-rendered", "ground truth normals"):
        assert text in page, text
    if shipped_weights(10)[0]:
        assert "network normals" in page and "visual hull normals" in page
    # reconstruct's own report has no ground truth
    assert "ground truth normals" not in without_gt and '"ground_truth"' not in without_gt


def test_report_in_headless_chromium(small_run, tmp_path, record_property):
    """The page loads in Chromium without a console error or a request, and its 3D view draws:
    the canvas's screenshot is not blank. A copy of the page with an error and a request in it is
    caught, so the check is not blind."""
    binary = find_chromium()
    if binary is None:
        pytest.skip(NO_CHROMIUM)
    import cv2

    root, _ = small_run
    html = root / "out" / "report.html"
    load = load_page(html, binary)
    for name, png in (("first_screen", load.screen), ("canvas", load.canvas), ("view", load.view)):
        (tmp_path / f"{name}.png").write_bytes(png)
    record_property("screenshots", str(tmp_path))
    print(f"\nthe report in headless chromium: {tmp_path}/first_screen.png (the first screen), canvas.png (the "
          "WebGL drawing), view.png (the 3D view as shown)")
    assert load.console == [] and load.log.get("errors") == [], (load.console, load.log)
    assert load.requests == [] and load.log.get("resources") == [], (load.requests, load.log)
    assert load.log["rendered"] and load.log["layers"] == len(scene_data(html.read_text())["layers"])
    for png in (load.canvas, load.view):  # the drawing alone, and as shown
        image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(np.float32)
        assert image.shape[0] > 300 and image.shape[1] > 400, image.shape
        background = np.median(image.reshape(-1, 3), axis=0)
        drawn = np.abs(image - background).max(axis=-1) > 20
        assert image.std() > 10 and drawn.mean() > 0.03, (image.std(), drawn.mean())
        # the middle, where the object is, is drawn and shaded (more than one colour)
        h, w = image.shape[:2]
        middle = image[h // 3:2 * h // 3, w // 3:2 * w // 3]
        assert np.abs(middle - background).max(axis=-1).mean() > 20 and middle.std() > 10
    # not blind: a picture from the network (blocked by the page's policy) and a script error
    bad = tmp_path / "bad.html"
    bad.write_text(html.read_text().replace("</body>", '<img src="http://example.invalid/x.png">'
                                                       "<script>undefinedFunction();</script></body>"))
    caught = load_page(bad, binary, timeout=30)
    assert any("example.invalid" in e for e in caught.log["errors"]) and any("undefinedFunction" in e for e in caught.console)


def test_view_opens_the_report_or_prints_its_path(small_run, tmp_path):
    root, _ = small_run
    seen = []
    path, opened = open_report(root / "out", opener=lambda url: seen.append(url) or True)
    assert opened and seen == [(root / "out" / "report.html").resolve().as_uri()]
    assert open_report(root / "out" / "report.html", opener=lambda url: False) == (path, False)
    # the command: $BROWSER is the default browser; with none, the path alone
    browser = tmp_path / "browser.sh"
    browser.write_text(f"#!/bin/sh\necho \"$1\" > {tmp_path / 'opened.txt'}\n")
    browser.chmod(0o755)
    proc = run("view", root / "out", env={**os.environ, "BROWSER": str(browser)})
    assert proc.stdout.strip() == str(path)
    assert (tmp_path / "opened.txt").read_text().strip() in (str(path), path.as_uri())
    proc = run("view", tmp_path, ok=False)
    assert proc.returncode == 2 and "report.html" in proc.stderr and "Traceback" not in proc.stderr


def test_display_meshes_and_colours():
    sphere = trimesh.creation.icosphere(subdivisions=6)  # 81920 faces
    small = display_mesh(sphere, 5000)
    assert 4000 <= len(small.faces) <= 5000 and small.is_watertight
    np.testing.assert_allclose(small.bounds, sphere.bounds, atol=0.02)
    assert display_mesh(sphere, 10**6).faces.shape == sphere.faces.shape
    ends = colormap(np.array([0.0, 1.0, 2.0]))
    np.testing.assert_allclose(ends[0], [int(COLORMAP[0][i:i + 2], 16) / 255 for i in (1, 3, 5)])
    np.testing.assert_allclose(ends[1], ends[2])
    assert [nice_ceiling(x) for x in (0.031, 0.05, 0.21, 7)] == [0.05, 0.05, 0.25, 10]
