"""OUT/report.html: one self-contained page showing a reconstruction, for people.

`write_report` gathers a `reconstruct` output folder (report.json, mesh.ply, visual_hull.ply,
normals/) and its capture into one HTML file that opens offline in any browser:

- a 3D view (three.js, bundled: lookingglass/report/static/, rebuilt by scripts/build_report_js.sh)
  of the result, the visual hull and the ground truth when known, with the input cameras as
  frusta and the result coloured by its distance to the ground truth;
- per view: the photo with the mask's outline, the result re-rendered as glass under the capture's
  environment map by the project's renderer (`render.compare.rerender`), the hull's, the network's,
  the result's and the ground truth's normals, and the re-rendering error;
- the numbers: metrics against the ground truth (hull vs result), per-stage time and memory, render
  errors, warnings, the config.

The page loads nothing: meshes are GLB and pictures PNG/JPEG data URIs, the scripts are inline,
and a Content-Security-Policy of `default-src 'none'` forbids every request. `open_report` shows it
in the default browser (`lookingglass view OUT`).
"""

from .build import REPORT_NAME, write_report
from .view import open_report

__all__ = ["REPORT_NAME", "write_report", "open_report"]
