"""The figure of docs/capture.md (docs/capture.png), from a synthetic capture made on the spot
(tests/capture_synth.py's `capture_shoot`: 9 photos of a glass sphere and 3 of a mirror ball in
its place, 480x360, a distorting camera, a room papered with discs):

    OMP_NUM_THREADS=1 python scripts/capture_figure.py [--out docs/capture.png]

runs `sfm` and `envmap-from-ball` (ball detected, no circles file) on it and draws: the three ball
photos with the circle the calibration chose (green) and the other candidates (thin red); the true
environment map beside the recovered one, rotated into the true frame; the camera centres seen from
above, true and recovered (after the similarity that maps the recovered centres onto the true ones).
About 20 s on one core; the numbers drawn are that run's (SfM is not bit-stable across runs).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

GREEN, RED, WHITE, GREY = (40, 230, 40), (230, 50, 30), (255, 255, 255), (110, 110, 110)  # RGB


def _title(panel: np.ndarray, text: str) -> np.ndarray:
    """The panel (H, W, 3) uint8 with a 16 px title bar above it."""
    bar = np.zeros((16, panel.shape[1], 3), np.uint8)
    cv2.putText(bar, text, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, WHITE, 1, cv2.LINE_AA)
    return np.concatenate([bar, panel], 0)


def _shown(image: np.ndarray, scale: float, size: tuple[int, int]) -> np.ndarray:
    """Linear radiance (H, W, 3) for display: divided by `scale`, resized to size (W, H), sRGB uint8."""
    from lookingglass.capture.images import linear_to_srgb

    small = cv2.resize(np.asarray(image, np.float32) / scale, size, interpolation=cv2.INTER_AREA)
    return np.round(linear_to_srgb(small) * 255).astype(np.uint8)


def _circle(img: np.ndarray, circle, factor: float, colour, thickness: int) -> None:
    """Draw a circle (cx, cy, r in continuous photo pixels) on img, a copy scaled by `factor`."""
    cx, cy, r = (v * factor for v in circle)
    cv2.circle(img, (round((cx - 0.5) * 16), round((cy - 0.5) * 16)), round(r * 16), colour, thickness,
               cv2.LINE_AA, shift=4)


def _poses(true_o: np.ndarray, est_o: np.ndarray, is_ball: np.ndarray, radius: float, size: int = 240) -> np.ndarray:
    """Camera centres from above (x right, z down), true (white rings) and recovered (red dots), the
    ball views' rings green; the object (radius `radius`) at the origin (grey disc)."""
    img = np.zeros((size, size, 3), np.uint8)
    extent = 1.15 * np.abs(true_o[:, [0, 2]]).max()
    to_px = lambda p: (round((p[0] / extent + 1) * size / 2), round((p[2] / extent + 1) * size / 2))  # noqa: E731
    cv2.circle(img, to_px(np.zeros(3)), max(2, round(radius / extent * size / 2)), GREY, -1, cv2.LINE_AA)
    for t, e, b in zip(true_o, est_o, is_ball):
        cv2.circle(img, to_px(t), 6, GREEN if b else WHITE, 1, cv2.LINE_AA)
        cv2.circle(img, to_px(e), 2, RED, -1, cv2.LINE_AA)
    return img


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "capture.png")
    args = parser.parse_args()

    from capture_synth import OBJECT_CENTRE, OBJECT_RADIUS, capture_shoot, log_luminance_correlation, similarity
    from lookingglass.capture.ball import ball_candidates, envmap_from_ball
    from lookingglass.capture.colmap import read_model
    from lookingglass.capture.config import BallConfig
    from lookingglass.capture.images import read_envmap, read_image
    from lookingglass.capture.sfm import run_sfm
    from lookingglass.data.envmaps import resize_envmap
    from lookingglass.fileio import write_atomic
    from lookingglass.physics.environment import rotate_envmap

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        truth = capture_shoot(tmp, 12, (2, 6, 9), 480, 360)
        run_sfm([tmp / "photos", tmp / "ball"], tmp / "sfm", tmp / "masks")
        record = envmap_from_ball(tmp / "sfm", tmp / "ball", tmp / "env.hdr", size=(256, 128),
                                  config=BallConfig(reflectance=0.8))
        model = read_model(tmp / "sfm")
        index = [int(v.stem.split("_")[1]) for v in model.views]
        est_o, true_o = np.stack([v.origin for v in model.views]), truth["cams"].origin.numpy()[index]
        s, R, t = similarity(est_o, true_o)
        centre_err = np.linalg.norm(s * est_o @ R.T + t - true_o, axis=1).max() / 2.5

        photos = []
        for view in record["views"]:
            img = read_image(view["photo"])
            small = _shown(img, 2 * float(np.median(img)), (240, 180))
            for other, _ in ball_candidates(img):
                _circle(small, other, 0.5, RED, 1)
            _circle(small, view["circle"], 0.5, GREEN, 2)
            photos.append(_title(small, f"{Path(view['photo']).name}: fit {view['residual_px']:.2f} px RMS"))
        true_env = resize_envmap(truth["env"], 128)
        est_env = rotate_envmap(torch.from_numpy(read_envmap(tmp / "env.hdr")).double(),
                                torch.from_numpy(R)).numpy()
        corr = log_luminance_correlation(est_env, true_env)
    scale = 2 * float(np.median(true_env))
    envs = np.concatenate([_title(_shown(true_env, scale, (240, 120)), "true environment map"),
                           _title(_shown(est_env, scale, (240, 120)),
                                  f"from the ball (log-lum corr {corr:.3f})")], 0)
    ball_err = np.linalg.norm(s * R @ record["centre"] + t - OBJECT_CENTRE) / OBJECT_RADIUS
    poses = _title(_poses(true_o, s * est_o @ R.T + t, np.array(["ball" in v.name for v in model.views]),
                          OBJECT_RADIUS),
                   f"cameras from above: centres {100 * centre_err:.2f}%")
    poses = np.pad(poses, ((0, envs.shape[0] - poses.shape[0]), (0, 0), (0, 0)))
    note = np.zeros((envs.shape[0], 720 - envs.shape[1] - poses.shape[1], 3), np.uint8)
    for k, line in enumerate(["white: true camera", "green: its ball view", "red: sfm, aligned",
                              f"ball centre {100 * ball_err:.2f}% of r", f"radius {100 * (s * record['radius'] / OBJECT_RADIUS - 1):+.2f}%"]):
        cv2.putText(note, line, (6, 30 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.38, WHITE, 1, cv2.LINE_AA)
    figure = np.concatenate([np.concatenate(photos, 1), np.concatenate([envs, poses, note], 1)], 0)
    write_atomic(args.out, lambda p: cv2.imwrite(str(p), np.ascontiguousarray(figure[..., ::-1])))
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KB); ball centre {100 * ball_err:.2f}% of r, "
          f"camera centres {100 * centre_err:.2f}% of the distance, map log-lum corr {corr:.3f}")


if __name__ == "__main__":
    main()
