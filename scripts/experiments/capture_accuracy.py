"""An experiment (issue 26, item 5): `lookingglass capture` on the synthetic shoot of tests/test_capture_real.py's
end-to-end test, at a chosen photo size and scene size, and the figures the issue asks for: camera rotations and
centres after a similarity alignment, the ball's centre and radius, the map's log-luminance correlation with the
truth, and the visual hull's CD against the hull carved from the true cameras at the same settings.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/experiments/capture_accuracy.py [PHOTO_W PHOTO_H SCENE_W SCENE_H [VIEWS
        BALL_VIEWS]]

(480 360 160 120 12 2,6,9 is the test's: 12 photos, 3 of them of the ball; the object's radius is ~1/9 of the
photo's width.)
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]



def main(pw: int, ph: int, sw: int, sh: int, views: int = 12, ball_views: tuple[int, ...] = (2, 6, 9)) -> None:
    from capture_synth import capture_figures, capture_shoot
    from cli_helpers import run

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        truth = capture_shoot(tmp, views, ball_views, pw, ph)
        print(f"shoot {pw}x{ph} made in {time.perf_counter() - t:.0f} s", flush=True)
        t = time.perf_counter()
        run("capture", "--photos", tmp / "photos", "--ball", tmp / "ball", "--masks", tmp / "masks", "--out", tmp / "work",
            "--size", sw, sh, "--envmap-size", 64, 32, "--ball.reflectance", 0.8, "--stop-after", "visual_hull")
        print(f"capture in {time.perf_counter() - t:.0f} s", flush=True)
        unregistered = json.loads((tmp / "work" / "sfm" / "sfm.json").read_text())["unregistered"]
        f = capture_figures(truth, tmp / "work", (sw, sh))
    print(json.dumps({"photos": [pw, ph], "scene": [sw, sh], "views": views, "ball_views": list(ball_views),
                      "unregistered": unregistered,
                      "rotation_err_deg_max": round(float(f["rotation_err_deg"].max()), 3),
                      "centre_err_pct_max": round(100 * float(f["centre_err"].max()), 3),
                      "ball_centre_err_pct_radius": round(100 * f["ball_centre_err"], 2),
                      "ball_radius_err_pct": round(100 * f["ball_radius_err"], 2),
                      "envmap_log_luminance_corr": round(float(f["envmap_corr"]), 3),
                      "hull_cd": round(f["hull_cd"], 3), "hull_cd_true_cameras": round(f["hull_cd_true_cameras"], 3),
                      "hull_cd_ratio": round(f["hull_cd"] / f["hull_cd_true_cameras"], 3),
                      "hull_cd_fitted_ratio": round(f["hull_cd_fitted"] / f["hull_cd_true_cameras_fitted"], 3)},
                     indent=1))


if __name__ == "__main__":
    sizes = [int(v) for v in sys.argv[1:5]] if len(sys.argv) >= 5 else [480, 360, 160, 120]
    shoot = (int(sys.argv[5]), tuple(int(v) for v in sys.argv[6].split(","))) if len(sys.argv) >= 7 else ()
    main(*sizes, *shoot)
