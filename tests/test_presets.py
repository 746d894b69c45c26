"""The named presets (lookingglass.presets): one registry, four typed configs each, checked values."""

import dataclasses

import pytest

from lookingglass.config import PipelineConfig
from lookingglass.configio import config_from_dict, config_to_dict
from lookingglass.data.dataset import DatasetConfig
from lookingglass.errors import ConfigError, LookingGlassError
from lookingglass.normals import model as normal_model
from lookingglass.normals.train import TrainConfig
from lookingglass.points import model as point_model
from lookingglass.points.train import PointTrainConfig
from lookingglass.presets import DEFAULT_PRESET, PRESET_NAMES, Preset, preset


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_every_preset_builds_all_four_configs(name):
    chosen = preset(name)
    assert isinstance(chosen, Preset) and chosen.name == name
    assert isinstance(chosen.pipeline, PipelineConfig) and isinstance(chosen.dataset, DatasetConfig)
    assert isinstance(chosen.normal_training, TrainConfig) and isinstance(chosen.point_training, PointTrainConfig)
    # the networks train at the dataset's resolution
    net = chosen.normal_training.net
    assert (net.width, net.height) == (chosen.dataset.width, chosen.dataset.height)
    assert chosen.dataset.preset == name
    # each config survives its JSON form (config.json, report.json)
    for config in (chosen.pipeline, chosen.dataset, chosen.normal_training, chosen.point_training):
        assert config_from_dict(type(config), config_to_dict(config)) == config


def test_cpu_preset_values():
    cpu = preset("cpu")
    assert DEFAULT_PRESET == "cpu" and cpu.pipeline == PipelineConfig() and cpu.dataset == DatasetConfig()
    normals = cpu.normal_training
    assert (normals.epochs, normals.lr, normals.lr_halve_epochs, normals.views_per_step) == (8, 4e-4, 3, 4)
    assert normals.net == normal_model.cpu_config() and normals.net.num_views == 10
    points = cpu.point_training
    assert (points.epochs, points.lr, points.lr_halve_epochs, points.checkpoint_every) == (6, 3e-4, 2, 100)
    assert points.net == point_model.cpu_config() and points.net.num_points == 4096


def test_paper_preset_values():
    paper = preset("paper")
    latent = paper.pipeline.normals.latent
    assert (latent.iterations_n2, latent.iterations_both) == (500, 500)
    assert dataclasses.replace(paper.pipeline, normals=PipelineConfig().normals) == PipelineConfig()
    data = paper.dataset
    assert (data.width, data.height, data.envmap_height, data.samples_per_axis) == (256, 192, 256, 3)
    assert paper.normal_training == TrainConfig(net=normal_model.paper_config())
    assert paper.point_training == PointTrainConfig(net=point_model.paper_config())


def test_presets_are_fresh_copies_and_unknown_names_are_refused():
    first = preset("cpu")
    first.pipeline.hull.resolution = 64
    assert preset("cpu").pipeline.hull.resolution == 128
    with pytest.raises(ConfigError, match="unknown preset 'gpu'.*cpu, paper"):
        preset("gpu")


def test_configs_check_their_ranges_when_built_or_replaced():
    """A value out of range is a ConfigError (a LookingGlassError and a ValueError) naming the
    field, whether the config is built, edited with dataclasses.replace or loaded from JSON."""
    cpu = preset("cpu")
    with pytest.raises(ConfigError, match=r"resolution must be in \[16, 1024\], got 8"):
        dataclasses.replace(cpu.pipeline.hull, resolution=8)
    with pytest.raises(ConfigError, match="epochs must be at least 1"):
        dataclasses.replace(cpu.normal_training, epochs=0)
    with pytest.raises(ConfigError, match="iterations_n2 must be at least 0"):
        dataclasses.replace(cpu.pipeline.normals.latent, iterations_n2=-1)
    with pytest.raises(ConfigError, match="NE or RE"):
        dataclasses.replace(cpu.point_training, loss="view", strategy="AV")
    with pytest.raises(ConfigError, match="p_procedural"):
        dataclasses.replace(cpu.dataset, p_procedural=1.5)
    bad = config_to_dict(cpu.pipeline)
    bad["surface"]["depth"] = 0
    with pytest.raises(ConfigError, match="depth must be in"):
        config_from_dict(PipelineConfig, bad)
    assert issubclass(ConfigError, LookingGlassError) and issubclass(ConfigError, ValueError)
