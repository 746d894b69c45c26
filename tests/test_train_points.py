"""Point-net training: the feature cache is made once and reused, the loss decreases, resume is
exact, weights load back, another config in the same folder is refused, and the CLI runs.
(The shared loop's torchrun path is covered by tests/test_train_normals.py.)"""

import dataclasses
import hashlib
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from lookingglass.config import PipelineConfig
from lookingglass.data.dataset import DatasetConfig, generate_dataset
from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.errors import LookingGlassError
from lookingglass.normals.model import cpu_config as normal_cpu_config
from lookingglass.normals.train import TrainConfig, train_normals
from lookingglass.points.features import FEATURE_COLUMNS, NUM_FEATURES, PAPER_FEATURES
from lookingglass.points.model import PointNetConfig
from lookingglass.weights import load_normal_net, load_point_net, shipped_weights
from lookingglass.points.train import TRAINING_FEATURES, PointTrainConfig, prepare_features, train_points
from lookingglass.presets import preset


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """3 scenes of 5 views at 64x48 and a normal net trained for 2 steps on them."""
    root = tmp_path_factory.mktemp("points_data")
    cfg = DatasetConfig(width=64, height=48, envmap_height=32, samples_per_axis=1)
    generate_dataset(root / "data", 3, views=5, split="train", seed=0, config=cfg, workers=1)
    net = normal_cpu_config(width=64, height=48, num_views=5, enc_channels=(16, 32, 64), fnet_channels=16)
    train_normals(TransparentSceneDataset(root / "data", "train"), root / "normals",
                  TrainConfig(net=net, epochs=1, lr=1e-3, max_scenes=2))
    return root / "data", root / "normals" / "weights.safetensors"


def _config(epochs=3, loss="chamfer"):
    net = PointNetConfig(num_points=512, centres=(128, 32), radii=(0.2, 0.4), neighbours=(16, 16),
                         sa_mlps=((16, 16), (32, 32)), fp_mlps=((32,), (16,)), gn_group_size=8, residual=True)
    return PointTrainConfig(net=net, loss=loss, epochs=epochs, lr=1e-3, checkpoint_every=2)


def _log(run):
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def test_training_caches_features_lowers_loss_and_ships_weights(tiny, tmp_path):
    data, normals = tiny
    ds = TransparentSceneDataset(data, "train", augment=False)
    run = tmp_path / "run"
    train_points(ds, run, _config(epochs=4), normals)
    cached = sorted((run / "features").glob("scene_*.npz"))
    assert len(cached) == 3
    with np.load(cached[0]) as z:
        assert z["features"].shape == (512, NUM_FEATURES) and z["features"].dtype == np.float32
        assert z["gt_points"].shape == (512, 3) and z["gt_normals"].dtype == np.float32
    log = _log(run)
    assert len(log) == 4 and log[-1]["step"] == 12
    assert log[-1]["loss"] < log[0]["loss"] and log[-1]["loss"] < log[-1]["loss_input"]
    net = load_point_net(run / "weights.safetensors").net
    assert net.cfg == _config().net
    assert json.loads((run / "weights.json").read_text())["loss"] == "chamfer"

    # The cache is reused: a finished run run again remakes nothing; a deleted file is remade alone.
    mtimes = [p.stat().st_mtime_ns for p in cached]
    train_points(ds, run, _config(epochs=4), normals)
    assert [p.stat().st_mtime_ns for p in cached] == mtimes
    cached[1].unlink()
    summary = prepare_features(ds, run, _config(epochs=4), load_normal_net(normals))
    assert summary["made"] == [1] and summary["skipped"] == 2

    with pytest.raises(LookingGlassError, match="different config"):
        train_points(ds, run, _config(epochs=5), normals)
    with pytest.raises(LookingGlassError, match="normals-network weights"):
        load_point_net(normals).net


def test_unseen_weight_weighs_the_input_loss_as_the_step_does(tiny, tmp_path):
    """--unseen-weight: the logged loss of the untouched input is the weighted Chamfer loss of the cached hull points
    (with the weights `unseen_weights` gives them), recomputed here from the cache; 0 is the paper's loss."""
    from lookingglass.points.losses import chamfer_loss, unseen_weights
    data, normals = tiny
    ds = TransparentSceneDataset(data, "train", augment=False)
    cfg = dataclasses.replace(_config(epochs=1), lr=0.0, unseen_weight=8.0, unseen_distance=0.02)
    train_points(ds, tmp_path / "w", cfg, normals)
    xyz, mapped = FEATURE_COLUMNS["point"], FEATURE_COLUMNS["normal"]
    want = {}
    for weight in (8.0, 0.0):
        totals = []
        for path in sorted((tmp_path / "w" / "features").glob("scene_*.npz")):
            with np.load(path) as z:
                f, q, nq = (torch.from_numpy(z[k])[None] for k in ("features", "gt_points", "gt_normals"))
            w = unseen_weights(q, f[..., xyz], weight, 0.02)
            totals.append(chamfer_loss(f[..., xyz], torch.nn.functional.normalize(f[..., mapped], dim=-1), q, nq,
                                       gt_weights=w).total.item())
        want[weight] = float(np.mean(totals))
    assert _log(tmp_path / "w")[0]["loss_input"] == pytest.approx(want[8.0], rel=1e-5)
    assert want[8.0] > 1.02 * want[0.0]  # these coarse hulls span some ground truth (+3.5%): the weights act
    meta = json.loads((tmp_path / "w" / "weights.json").read_text())
    assert (meta["unseen_weight"], meta["unseen_distance"]) == (8.0, 0.02)


def test_resume_after_interruption_is_exact(tiny, tmp_path):
    data, normals = tiny
    ds = TransparentSceneDataset(data, "train", augment=False)
    cfg = _config(epochs=3, loss="nearest")
    train_points(ds, tmp_path / "full", cfg, normals)
    shutil.copytree(tmp_path / "full" / "features", tmp_path / "part" / "features")  # same cache, less time
    # Interrupted after 4 steps (mid-epoch 2, after a step checkpoint), then resumed to the end.
    train_points(ds, tmp_path / "part", cfg, normals, max_steps=4)
    train_points(ds, tmp_path / "part", cfg, normals)
    assert _log(tmp_path / "part")[-1]["step"] == 9
    a = load_point_net(tmp_path / "full" / "weights.safetensors").net.state_dict()
    b = load_point_net(tmp_path / "part" / "weights.safetensors").net.state_dict()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-5, atol=1e-7)


def test_init_starts_from_given_weights(tiny, tmp_path):
    """--init: a run starts from another run's weights (lr 0 keeps them exactly), records their
    SHA-256, and refuses weights of another network. Weights for the paper's 12 input columns
    start a net that also reads the silhouette counts, with zero weights for the new columns:
    the same function; never the other way round."""
    data, normals = tiny
    ds = TransparentSceneDataset(data, "train", augment=False)
    base = tmp_path / "base"
    narrow = _config(epochs=2)
    narrow.net = dataclasses.replace(narrow.net, in_features=PAPER_FEATURES)
    train_points(ds, base, narrow, normals)
    init = base / "weights.safetensors"
    shutil.copytree(base / "features", tmp_path / "tuned" / "features")
    tuned = dataclasses.replace(_config(epochs=1), lr=0.0, init=str(init))
    assert tuned.net.in_features == NUM_FEATURES > PAPER_FEATURES
    train_points(ds, tmp_path / "tuned", tuned, normals)
    a, b = load_point_net(init).net, load_point_net(tmp_path / "tuned" / "weights.safetensors").net
    sa, sb = a.state_dict(), b.state_dict()
    widened = {"sa.0.mlp.0.weight", f"fp.{len(b.fp) - 1}.mlp.0.weight"}
    for k in sa:
        if k not in widened:
            torch.testing.assert_close(sa[k], sb[k], rtol=0, atol=0)
        else:  # PAPER_FEATURES - NUM_FEATURES new zero columns, the rest as they were
            assert sb[k].shape[1] == sa[k].shape[1] + NUM_FEATURES - PAPER_FEATURES
            assert (sb[k] != 0).any(0).sum() == (sa[k] != 0).any(0).sum()
    with np.load(next((base / "features").glob("scene_*.npz"))) as z:
        features = torch.from_numpy(z["features"])[None]
    assert features[..., FEATURE_COLUMNS["silhouette"]].abs().sum() > 0  # the new columns carry data
    with torch.no_grad():
        for x, y in zip(a(features), b(features)):  # float32: wider matmuls sum in another order
            torch.testing.assert_close(x, y, rtol=0, atol=1e-5)
    meta = json.loads((tmp_path / "tuned" / "weights.json").read_text())
    assert meta["init_sha256"] == hashlib.sha256(init.read_bytes()).hexdigest()
    # Starting from them at a working rate continues below where the base run ended.
    shutil.copytree(base / "features", tmp_path / "more" / "features")
    train_points(ds, tmp_path / "more", dataclasses.replace(_config(epochs=1), init=str(init)), normals)
    assert _log(tmp_path / "more")[0]["loss"] < _log(base)[0]["loss"]

    other = dataclasses.replace(_config(epochs=1), init=str(init))
    other.net = dataclasses.replace(other.net, sa_mlps=((8, 8), (32, 32)))
    with pytest.raises(LookingGlassError, match="another network .*sa_mlps"):
        train_points(ds, tmp_path / "other", other, normals)
    fewer = dataclasses.replace(narrow, init=str(tmp_path / "tuned" / "weights.safetensors"))
    with pytest.raises(LookingGlassError, match="another network .*in_features"):
        train_points(ds, tmp_path / "fewer", fewer, normals)
    with pytest.raises(LookingGlassError, match="--init weights not found"):
        train_points(ds, tmp_path / "missing", dataclasses.replace(_config(epochs=1), init=str(tmp_path / "x.safetensors")),
                     normals)
    # A cache made before the silhouette columns existed is refused, not mixed.
    source = base / "features" / "source.json"
    recorded = json.loads(source.read_text())
    assert recorded["consensus_px"] == TRAINING_FEATURES.consensus_px and recorded["mirror_average"]
    source.write_text(json.dumps({k: v for k, v in json.loads(source.read_text()).items() if k != "feature_columns"}))
    with pytest.raises(LookingGlassError, match="feature columns"):
        train_points(ds, base, narrow, normals)
    # So is one made by another normal stage (before session 92's: each view's own prediction).
    source.write_text(json.dumps({**{k: v for k, v in recorded.items() if k != "mirror_average"}}))
    with pytest.raises(LookingGlassError, match="normal stage"):
        train_points(ds, base, narrow, normals)


def test_training_features_come_from_reconstructs_normal_stage():
    """PNet learns from what `reconstruct` feeds it: the features' normal stage is the pipeline's default."""
    assert TRAINING_FEATURES == PipelineConfig().normals


def test_view_loss_targets(tiny, tmp_path):
    data, normals = tiny
    ds = TransparentSceneDataset(data, "train", augment=False)
    cfg = _config(epochs=1, loss="view")
    cfg.max_scenes = 1
    metrics = train_points(ds, tmp_path / "view", cfg, normals)
    assert metrics["step"] == 1 and np.isfinite(metrics["loss"])
    with np.load(next((tmp_path / "view" / "features").glob("scene_*.npz"))) as z:
        assert z["view_valid"].dtype == bool and z["view_valid"].mean() > 0.5
        assert z["view_points"].shape == z["nearest_points"].shape == (512, 3)
    with pytest.raises(LookingGlassError, match="NE or RE"):
        PointTrainConfig(loss="view", strategy="AV")
    with pytest.raises(LookingGlassError, match="unknown point loss"):
        PointTrainConfig(loss="nope")
    with pytest.raises(LookingGlassError, match="unseen-weight"):
        PointTrainConfig(loss="nearest", unseen_weight=4.0)
    assert preset("cpu").point_training.net.num_points == 4096


def test_cli_train_points(tiny, tmp_path):
    data, normals = tiny
    cmd = [sys.executable, "-m", "lookingglass.cli", "train-points", "--data", str(data), "--normals", str(normals),
           "--preset", "cpu", "--max-scenes", "2", "--epochs", "1", "--device", "cpu", "--quiet",
           "--out", str(tmp_path / "cli")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = _log(tmp_path / "cli")
    assert log[0]["step"] == 2 and log[0]["processes"] == 1
    assert load_point_net(tmp_path / "cli" / "weights.safetensors").net.cfg.num_points == 4096


def test_cli_refuses_normals_of_another_image_size(tiny, tmp_path):
    """The shipped 5-view net (128x96) on this 64x48 data: refused naming both, before the run folder is made
    (it was found scene by scene after config.json and features/ were written)."""
    data, _ = tiny
    shipped = shipped_weights(5)[0]
    if shipped is None:
        pytest.skip("no 5-view weights ship in this build")
    cmd = [sys.executable, "-m", "lookingglass.cli", "train-points", "--data", str(data), "--normals", str(shipped),
           "--device", "cpu", "--quiet", "--out", str(tmp_path / "run")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 2 and "64x48" in proc.stderr and "128x96" in proc.stderr and str(shipped) in proc.stderr
    assert not (tmp_path / "run").exists()
