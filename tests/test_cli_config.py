"""Config options generated from the dataclasses (lookingglass/cliconfig.py): --help shows them
with the preset's defaults, given values land over the chosen preset, bad ones are one clear line."""

import functools
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from typer.testing import CliRunner

from cli_helpers import run_here
from lookingglass import cli
from lookingglass.normals.model import cpu_config as normal_cpu_config
from lookingglass.presets import preset

CLI = [sys.executable, "-m", "lookingglass.cli"]
# rich shortens long option names in narrow help; this checkout's package whatever the cwd
WIDE = {**os.environ, "COLUMNS": "250", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}


@functools.lru_cache(maxsize=None)
def help_text(command: str) -> str:
    """`command --help`, wide enough that each option fits one line (one process a command)."""
    proc = subprocess.run([*CLI, command, "--help"], capture_output=True, text=True, timeout=120, env=WIDE)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def help_line(command: str, flag: str) -> str:
    """The --help row of `flag` in `command`'s help."""
    text = help_text(command)
    rows = [line for line in text.splitlines() if f" {flag} " in line or f" {flag}," in line]
    assert len(rows) == 1, (flag, text)
    return rows[0]


@pytest.mark.parametrize("command, flag, shown", [
    ("reconstruct", "--hull.resolution,--hull-resolution", ["Range: 16 to 1024", "[default: 128]"]),
    ("reconstruct", "--normals.latent.iterations-n2", ["(paper: 500)", "[default: 0]"]),
    ("reconstruct", "--surface.point-weight", ["[default: 4.0]"]),
    ("reconstruct", "--stop-after", ["[default: refine]"]),
    ("train-normals", "--net.groups", ["(paper: 16)", "[default: 8]"]),
    ("train-normals", "--epochs", ["(paper: 10)", "[default: 8]"]),
    ("train-normals", "--net.num-views,--views", ["[default: 10]"]),
    ("train-points", "--net.num-points", ["(paper: 20000)", "[default: 4096]"]),
    ("train-points", "--checkpoint-every", ["[default: 100]"]),
    ("generate", "--shape.target-faces", ["[default: 24000]"]),
    ("generate", "--ior-range", ["from 1.0 to 3.0", "[default: 1.4723, 1.4723]"]),
    ("generate", "--ior-per-shape", ["[default: 1]"]),
    ("reconstruct", "--ior", ["scene (scene.json's)", "or auto: estimated from the photos", "[default: scene]"]),
    ("reconstruct", "--ior-range", ["LO < HI", "[default: 1.3, 1.7]"]),
])
def test_help_lists_config_fields_with_the_presets_defaults(command, flag, shown):
    line = help_line(command, flag)
    assert all(text in line for text in shown), line


@pytest.mark.parametrize("args, said", [
    (["reconstruct", "no_scene", "--out", "o", "--hull.resolution", "8"], "--hull-resolution=8: resolution must be in"),
    (["reconstruct", "no_scene", "--out", "o", "--surface.point-weight", "-1"],
     "--surface.point-weight=-1.0: point_weight must be at least 0"),
    (["train-normals", "--data", "d", "--out", "o", "--epochs", "0"], "--epochs=0: epochs must be at least 1"),
    (["train-points", "--data", "d", "--normals", "n", "--out", "o", "--loss", "view", "--strategy", "AV"],
     "--loss=view, --strategy=AV:"),
    (["generate", "--out", "o", "--scenes", "1", "--samples-per-axis", "0"], "samples_per_axis must be at least 1"),
    (["reconstruct", "no_scene", "--out", "o", "--ior", "0.9"],
     "--ior=0.9: ior must be an index of refraction from 1.0 to 3.0 (glass is about 1.5), got 0.9"),
    (["reconstruct", "no_scene", "--out", "o", "--ior", "abc"],
     "--ior=abc: ior must be scene, auto or an index of refraction"),
    (["reconstruct", "no_scene", "--out", "o", "--ior-range", "1.7", "1.3"],
     "--ior-range=1.7 1.3: ior_range: LO must be below HI, got 1.7 1.3"),
    (["generate", "--out", "o", "--scenes", "1", "--ior-range", "1.3", "3.5"], "ior_range must be an index of "
                                                                                 "refraction from 1.0 to 3.0"),
])
def test_out_of_range_flag_is_one_line_naming_the_field(tmp_path, args, said):
    proc = run_here(*args, cwd=tmp_path, env={"COLUMNS": "250"})
    assert proc.returncode == 2 and said in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()


def test_given_values_land_over_the_chosen_preset_and_defaults_do_not(monkeypatch, tmp_path):
    """--preset paper keeps paper's 500 + 500 latent steps where no flag changes them; an alias, a
    nested field and a bool reach the config; options not given keep the preset's values."""
    seen = {}
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "scene.json").write_text("{}")  # the command checks the folder before the pipeline
    monkeypatch.setattr("lookingglass.pipeline.reconstruct",
                        lambda scene, out, config, **kw: seen.setdefault("config", config) and {"total_seconds": 0})
    result = CliRunner().invoke(cli.app, ["reconstruct", "scene", "--out", "o", "--preset", "paper", "--quiet",
                                          "--normals.latent.iterations-both", "7", "--hull-resolution", "64",
                                          "--surface.point-weight", "2", "--weights", "w.safetensors"])
    assert result.exit_code == 0, result.output
    config = seen["config"]
    assert (config.normals.latent.iterations_n2, config.normals.latent.iterations_both) == (500, 7)
    assert config.hull.resolution == 64 and config.surface.point_weight == 2.0
    assert config.normals.weights == "w.safetensors" and config.surface.points == 40000
    assert config.hull == type(config.hull)(resolution=64)


def test_train_normals_resolves_the_same_config_as_before(monkeypatch):
    """The run folder's config.json must not change for the same flags: cpu preset, --views 5,
    --variant wr, the dataset's resolution; given values override the preset's schedule."""
    seen = {}
    dataset = SimpleNamespace(config=SimpleNamespace(width=64, height=48))
    monkeypatch.setattr("lookingglass.data.torch_dataset.TransparentSceneDataset", lambda *a, **kw: dataset)
    monkeypatch.setattr("lookingglass.normals.train.train_normals",
                        lambda data, out, config, **kw: seen.setdefault("config", config))
    result = CliRunner().invoke(cli.app, ["train-normals", "--data", "d", "--out", "o", "--views", "5", "--variant",
                                          "wr", "--epochs", "2", "--lr", "2e-4", "--init", "w.safetensors",
                                          "--device", "cpu", "--quiet"])
    assert result.exit_code == 0, result.output
    net = normal_cpu_config(num_views=5, width=64, height=48, use_cost_volume=False)
    expected = preset("cpu").normal_training
    assert seen["config"] == type(expected)(net=net, epochs=2, lr=2e-4, lr_halve_epochs=3, views_per_step=4,
                                            init="w.safetensors")
