"""Normal-net training: loss decreases, checkpoints resume exactly, DDP with two CPU processes."""

import json
import os
import shutil
import subprocess
import sys

import pytest
import torch

from lookingglass.data.dataset import DatasetConfig, generate_dataset
from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.errors import LookingGlassError
from lookingglass.normals.model import cpu_config
from lookingglass.normals.train import TrainConfig, train_normals
from lookingglass.weights import load_normal_net


def load_weights(path):
    return load_normal_net(path).net


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("normals_data")
    cfg = DatasetConfig(width=64, height=48, envmap_height=32, samples_per_axis=1)
    generate_dataset(root, 4, views=5, split="train", seed=0, config=cfg, workers=1)
    return root


def _config(epochs=3):
    return TrainConfig(net=cpu_config(width=64, height=48, num_views=5, enc_channels=(16, 32, 64),
                                      fnet_channels=16), epochs=epochs, lr=1e-3, checkpoint_every=2)


def test_training_lowers_loss_and_ships_weights(tiny_dataset, tmp_path):
    ds = TransparentSceneDataset(tiny_dataset, "train")
    train_normals(ds, tmp_path / "run", _config(epochs=4))
    log = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert len(log) == 4 and log[-1]["loss"] < log[0]["loss"]
    net = load_weights(tmp_path / "run" / "weights.safetensors")
    assert net.cfg.num_views == 5
    with pytest.raises(LookingGlassError):
        train_normals(ds, tmp_path / "run", _config(epochs=5))  # a different config in the same folder


def test_resume_after_interruption_is_exact(tiny_dataset, tmp_path):
    ds = TransparentSceneDataset(tiny_dataset, "train")
    train_normals(ds, tmp_path / "full", _config())
    # Interrupted after 6 steps (mid-epoch 2), then resumed to the end.
    train_normals(ds, tmp_path / "part", _config(), max_steps=6)
    train_normals(ds, tmp_path / "part", _config())
    a = load_weights(tmp_path / "full" / "weights.safetensors").state_dict()
    b = load_weights(tmp_path / "part" / "weights.safetensors").state_dict()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-6)


def test_torchrun_two_processes(tiny_dataset, tmp_path):
    torchrun = shutil.which("torchrun", path=os.path.dirname(sys.executable))
    if torchrun is None:
        pytest.skip("torchrun not installed beside this Python")
    cmd = [torchrun, "--nproc_per_node=2", "--master_port=29517", "-m", "lookingglass.cli", "train-normals",
           "--data", str(tiny_dataset), "--views", "5", "--out", str(tmp_path / "ddp"), "--epochs", "1",
           "--device", "cpu", "--quiet", "--net.gain-head"]  # as shipped: a head no normal loss reads
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = [json.loads(line) for line in (tmp_path / "ddp" / "metrics.jsonl").read_text().splitlines()]
    assert log[0]["processes"] == 2 and log[0]["step"] == 2  # 4 scenes shared by 2 processes
    assert (tmp_path / "ddp" / "weights.safetensors").exists()


def test_random_view_subsets(tiny_dataset, tmp_path):
    from lookingglass.normals.train import select_views

    ds = TransparentSceneDataset(tiny_dataset, "train")
    sample = ds[0]
    sub = select_views(sample, 2, torch.Generator().manual_seed(0))
    assert sub["image"].shape[0] == 2 and sub["origin"].shape[0] == 2 and sub["envmap"].shape == sample["envmap"].shape
    cfg = _config(epochs=1)
    cfg.views_per_step = 2
    metrics = train_normals(ds, tmp_path / "sub", cfg)
    assert metrics["step"] == 4 and metrics["loss"] > 0


def test_init_across_view_counts(tiny_dataset, tmp_path):
    """--init: weights of a 10-view net start a 5-view run (the view count changes no parameter;
    lr 0 keeps them exactly and the new run keeps its own view count), but a net of other widths
    is refused before training starts."""
    import dataclasses

    ds = TransparentSceneDataset(tiny_dataset, "train")
    ten = _config(epochs=1)
    ten.net.num_views = 10
    train_normals(ds, tmp_path / "ten", ten, max_steps=1)
    init = tmp_path / "ten" / "weights.safetensors"
    assert load_weights(init).cfg.num_views == 10
    train_normals(ds, tmp_path / "five", dataclasses.replace(_config(epochs=1), lr=0.0, init=str(init)))
    five = load_weights(tmp_path / "five" / "weights.safetensors")
    assert five.cfg.num_views == 5 and five.cfg.theta_deg == 25.0  # the 5-view rig's cost-volume angle
    a, b = load_weights(init).state_dict(), five.state_dict()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0)
    wide = _config(epochs=1)
    wide.net.fnet_channels = 32
    with pytest.raises(LookingGlassError, match="another network.*fnet_channels"):
        train_normals(ds, tmp_path / "wide", dataclasses.replace(wide, init=str(init)))
    # refused before the run folder is made: its config.json would refuse the corrected rerun
    assert not (tmp_path / "wide").exists()


def test_angle_loss_is_the_angle():
    """`pixel_loss`: l2 is |n - t|^2 = 4 sin^2(a/2) (the paper's); angle is the chord 2 sin(a/2) less
    a Charbonnier rounding of width eps near 0, so its slope in the angle stays ~1 per radian from a
    few degrees on, where l2's grows with the error (a 2-degree miss weighs ~1/16 of a 20-degree one,
    not 1/100). Unknown loss names are refused."""
    from lookingglass.errors import ConfigError
    from lookingglass.normals.train import ANGLE_LOSS_EPS, pixel_loss
    angles = torch.deg2rad(torch.tensor([0.0, 2.0, 5.0, 20.0, 60.0]))
    t = torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(5, 3, 1, 1)
    n = torch.stack([angles.sin(), torch.zeros(5), angles.cos()], 1).view(5, 3, 1, 1)
    chord = 2 * torch.sin(angles / 2)
    torch.testing.assert_close(pixel_loss(n, t, "l2").flatten(), chord ** 2)
    angle = pixel_loss(n, t, "angle").flatten()
    torch.testing.assert_close(angle, (chord ** 2 + ANGLE_LOSS_EPS ** 2).sqrt() - ANGLE_LOSS_EPS)
    assert angle[0] == 0 and abs(float(angle[3] - angle[2]) / float(angles[3] - angles[2]) - 1) < 0.03
    assert 0.05 < float(angle[1] / angle[3]) < 0.07
    with pytest.raises(ConfigError, match="loss"):
        TrainConfig(loss="l1")


def test_hull_hinge_weighs_only_the_pixels_made_worse():
    """--hull-hinge w: a pixel whose prediction is further from the truth than the hull's normal
    counts (1 + w) x its loss less w x the hull's; one the net improves counts as before; N2 alike
    over its valid pixels."""
    from lookingglass.normals.train import normal_loss, pixel_loss
    tilt = lambda deg: torch.stack([torch.deg2rad(deg).sin(), torch.zeros_like(deg), torch.deg2rad(deg).cos()], 0)
    truth = tilt(torch.zeros(1, 2)).unsqueeze(0)  # (1,3,1,2)
    pred = tilt(torch.tensor([[10.0, 10.0]])).unsqueeze(0)
    hull = tilt(torch.tensor([[4.0, 20.0]])).unsqueeze(0)  # better than pred at pixel 0, worse at pixel 1
    t = dict(n1=truth, n2=truth, mask=torch.ones(1, 1, 2, dtype=torch.bool),
             n2_valid=torch.tensor([[[True, False]]]))
    lp, lh = pixel_loss(pred, truth, "angle").flatten(), pixel_loss(hull, truth, "angle").flatten()
    plain = normal_loss(pred, pred, t, "angle")
    torch.testing.assert_close(plain, lp.mean() + lp[0])
    hinged = normal_loss(pred, pred, t, "angle", (hull, hull), hinge=2.0)
    torch.testing.assert_close(hinged, plain + 2.0 * (lp[0] - lh[0]) / 2 + 2.0 * (lp[0] - lh[0]))
    torch.testing.assert_close(normal_loss(pred, pred, t, "angle", (pred, pred), hinge=2.0), plain)


def test_gain_head_learns_a_quantile_and_leaves_the_normals(tiny_dataset, tmp_path):
    """--gain-head-only: a head added to trained normals (their weights start it: --init without a
    head) learns while every other weight stays bit-exact; the pinball loss it minimizes is lowest
    at the asked quantile of the true gains (the hull's angle error minus the prediction's), a
    missing true N2 counts as a loss of NO_N2_GAIN_DEG, and pixels without a hull path do not
    count; a head-only run without --init or without a head is refused."""
    import dataclasses
    from lookingglass.errors import ConfigError
    from lookingglass.normals.train import NO_N2_GAIN_DEG, gain_head_loss

    config = _train_head_alone(tiny_dataset, tmp_path, "gain_head")

    # 100 pixels: the truth and the prediction at +z, the hull tilted 1..100 degrees from it, so the
    # true gain at pixel i is (i + 1) degrees
    def tilted(deg):
        a = torch.deg2rad(deg)
        return torch.stack([a.sin(), torch.zeros_like(a), a.cos()]).view(1, 3, 1, -1)

    deg = torch.arange(1.0, 101.0)
    truth = pred = tilted(torch.zeros(100))
    hull = tilted(deg)
    t = {"n1": truth, "n2": truth, "mask": torch.ones(1, 1, 100, dtype=torch.bool),
         "n2_valid": torch.ones(1, 1, 100, dtype=torch.bool)}
    loss = lambda g, q=0.8, **kw: float(gain_head_loss(torch.full((1, 2, 1, 100), g), pred, pred,  # noqa: E731
                                                        kw.get("h1", hull), hull, kw.get("t", t), q))
    assert loss(80.0) < min(loss(78.0), loss(82.0))
    assert loss(50.0, 0.5) < min(loss(48.0, 0.5), loss(52.0, 0.5))
    # no true N2 anywhere: the N2 gains are all NO_N2_GAIN_DEG, so the loss's N2 half is 0 there
    no_n2 = {**t, "n2_valid": torch.zeros(1, 1, 100, dtype=torch.bool)}
    both = float(gain_head_loss(torch.stack([torch.full((1, 100), 80.0), torch.full((1, 100), NO_N2_GAIN_DEG)]
                                            ).view(1, 2, 1, 100), pred, pred, hull, hull, no_n2, 0.8))
    assert both == pytest.approx(loss(80.0) / 2, rel=1e-5)
    # the hull without a path at half the pixels: only the others count
    gone = hull.clone()
    gone[..., 50:] = 0
    assert loss(40.0, h1=gone) < min(loss(38.0, h1=gone), loss(42.0, h1=gone))
    with pytest.raises(ConfigError, match="gain-head"):
        TrainConfig(gain_head_only=True, init=config.init)
    with pytest.raises(ConfigError, match="gain-head"):
        dataclasses.replace(config, init="")


def _train_head_alone(tiny_dataset, tmp_path, head: str) -> TrainConfig:
    """Trained normals, then `head` ("gain_head" or "detail_head") added and trained alone
    (--init from them, --HEAD-only): its loss falls while every other weight stays bit-exact.
    Returns the head's training config."""
    import dataclasses

    ds = TransparentSceneDataset(tiny_dataset, "train")
    train_normals(ds, tmp_path / "normals", _config(epochs=1))
    init = tmp_path / "normals" / "weights.safetensors"
    config = _config(epochs=3)
    config = dataclasses.replace(config, net=dataclasses.replace(config.net, **{head: True}), init=str(init),
                                 lr=1e-2, **{f"{head}_only": True})
    train_normals(ds, tmp_path / "head", config)
    log = [json.loads(line) for line in (tmp_path / "head" / "metrics.jsonl").read_text().splitlines()]
    assert log[-1]["loss"] < log[0]["loss"]
    before, after = load_weights(init).state_dict(), load_weights(tmp_path / "head" / "weights.safetensors").state_dict()
    assert set(after) - set(before) == {k for k in after if k.startswith(f"{head}.")} != set()
    for k in before:
        torch.testing.assert_close(before[k], after[k], rtol=0, atol=0)
    return config


def test_detail_head_learns_and_leaves_the_rest(tiny_dataset, tmp_path):
    """--detail-head-only: a detail head added to trained normals (their weights start it) lowers
    the normal loss while every other weight stays bit-exact."""
    _train_head_alone(tiny_dataset, tmp_path, "detail_head")


def test_whole_net_fine_tune_keeps_the_gain_head(tiny_dataset, tmp_path):
    """Fine-tuning the normals of a net with a gain head (no loss reads the head there, and DDP
    refuses weights without a gradient) leaves the head as --init gave it and trains the rest."""
    import dataclasses

    ds = TransparentSceneDataset(tiny_dataset, "train")
    base = _config(epochs=1)
    base.net.gain_head = True
    train_normals(ds, tmp_path / "a", base, max_steps=1)
    init = tmp_path / "a" / "weights.safetensors"
    train_normals(ds, tmp_path / "b", dataclasses.replace(base, init=str(init)))
    a, b = load_weights(init).state_dict(), load_weights(tmp_path / "b" / "weights.safetensors").state_dict()
    changed = {k for k in a if not torch.equal(a[k], b[k])}
    others = {k for k in a if not k.startswith("gain_head.")}
    assert changed <= others and len(changed) > len(others) // 2
