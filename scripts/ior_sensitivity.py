"""The error against the object's IoR on the variable-IoR test split, the pipeline told 1.4723 (the
paper's supplement, "Sensitivity analysis for IoR", its two plots). Scene 5i + k of the split is test
scene i (shape, rig, map) with the k-th of five IoRs, so each scene is plotted as its error minus the
same shape's at 1.4723 (from the fixed-IoR split): what the wrong IoR costs, without the spread between
shapes. Panels: the N1 and N2 mean angle errors (hull and network, wr+cv+op) and the final mesh's
CD and CDN-mean; dots per scene, lines the binned means.

    pip install -e ".[plots]"     # matplotlib
    W=lookingglass/weights/normals_10views.safetensors
    lookingglass eval-normals --data data/data10_varior --views 10 --max-scenes 60 --ior 1.4723 \\
        --weights wr+cv=$W --json normals_varior.json
    lookingglass eval-normals --data data/data10 --views 10 --max-scenes 12 --weights wr+cv=$W \\
        --json normals_fixed.json
    lookingglass eval-shapes --data data/data10_varior --views 10 --max-scenes 60 --ior 1.4723 \\
        --strategies RE --latent-iterations 0 --json shapes_varior.json
    lookingglass eval-shapes --data data/data10 --views 10 --max-scenes 12 \\
        --strategies RE --latent-iterations 0 --json shapes_fixed.json
    python scripts/ior_sensitivity.py normals_varior.json normals_fixed.json shapes_varior.json \\
        shapes_fixed.json data/data10_varior docs/ior_sensitivity.png
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.fileio import atomic_path
from lookingglass.physics.constants import IOR_GLASS

BINS = np.linspace(1.3, 1.7, 6)  # five bins of 0.08
IORS_PER_SHAPE = 5
COLOURS = {"vh": "#888888", "wr+cv+op": "#1f6fb4", "pnet-RE": "#e08a1e", "refined": "#2a9d4b"}
LABELS = {"vh": "visual hull", "wr+cv+op": "normal net (wr+cv+op)", "pnet-RE": "PNet surface",
          "refined": "refined mesh (reconstruct's)"}


def binned(ior: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bin centres and the mean of `values` in each (NaN where a bin is empty)."""
    which = np.clip(np.digitize(ior, BINS) - 1, 0, len(BINS) - 2)
    means = np.array([values[which == b].mean() if (which == b).any() else np.nan for b in range(len(BINS) - 1)])
    return (BINS[:-1] + BINS[1:]) / 2, means


def differences(varied: list[dict], fixed: dict[int, dict], metric: str) -> np.ndarray:
    """Each varied scene's `metric` minus its shape's at the known IoR (scene index // 5)."""
    return np.array([v[metric] - fixed[index // IORS_PER_SHAPE][metric] for index, v in varied])


def main(normals_varied: str, normals_fixed: str, shapes_varied: str, shapes_fixed: str, data: str, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    read = lambda path: json.loads(Path(path).read_text())  # noqa: E731
    nv, nf, sv, sf = read(normals_varied), read(normals_fixed), read(shapes_varied), read(shapes_fixed)
    dataset = TransparentSceneDataset(data, "test", views=sv["settings"].get("views", 10))
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.9))

    def panel(ax, ior, rows: dict[str, np.ndarray], title: str, unit: str) -> None:
        for row, values in rows.items():
            ax.scatter(ior, values, s=8, alpha=0.35, color=COLOURS[row])
            centre, mean = binned(ior, values)
            ax.plot(centre, mean, "-o", color=COLOURS[row], label=LABELS[row], ms=4)
            print(f"{title[:30]:30s} {row:9s} bin means at {' '.join(f'{c:.2f}' for c in centre)}: "
                  f"{' '.join(f'{m:+.3f}' for m in mean)} (all {values.mean():+.3f})")
        ax.axvline(IOR_GLASS, color="k", lw=0.8, ls="--")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("object's IoR (the pipeline assumes 1.4723, dashed)", fontsize=8)
        ax.set_ylabel(unit, fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7)

    ior = np.array([s["ior"] for s in nv["scenes"]])
    fixed = {s["index"]: s["rows"] for s in nf["scenes"]}
    for ax, key, title in ((axes[0], "n1_mean", "N1 mean angle error"), (axes[1], "n2_mean", "N2 mean angle error")):
        rows = {row: differences([(s["index"], s["rows"][row]) for s in nv["scenes"]],
                                 {i: r[row] for i, r in fixed.items()}, key) for row in ("vh", "wr+cv+op")}
        panel(ax, ior, rows, title + ": minus the same shape's at 1.4723", "degrees")
    ior = np.array([float(dataset.meta(s["index"])["ior"]) for s in sv["scenes"]])
    fixed = {s["index"]: s for s in sf["scenes"]}
    shown = [row for row in ("pnet-RE", "refined") if row in sv["scenes"][0]]
    for ax, key, title, unit in ((axes[2], "cd", "final mesh CD", "CD (x1e4)"),
                                 (axes[3], "cdn_mean", "final mesh CDN-mean", "degrees")):
        rows = {row: differences([(s["index"], s[row]) for s in sv["scenes"]], {i: f[row] for i, f in fixed.items()}, key)
                for row in shown}
        panel(ax, ior, rows, title + ": minus the same shape's at 1.4723", unit)
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    print(f"wrote {out}")


if __name__ == "__main__":
    if len(sys.argv) != 7:
        sys.exit(__doc__)
    main(*sys.argv[1:])
