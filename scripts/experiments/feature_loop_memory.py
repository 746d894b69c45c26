"""The resident memory of train-points' feature loop (`points.train.prepare_features` itself, one
process, the shipped 10-view normal net), printed after each scene's features (before that scene's
garbage collection); docs/history.md, session 93.

Usage: .venv/bin/python scripts/experiments/feature_loop_memory.py DATA [SCENES]
(DATA: a 10-view training set, e.g. data/users10; 40 scenes by default; the cache goes to a
temporary folder.)
"""
import sys
import tempfile

import lookingglass.points.train as point_training
from lookingglass.data.torch_dataset import TransparentSceneDataset
from lookingglass.points.config import PointTrainConfig, cpu_config
from lookingglass.weights import load_normal_net, shipped_weights


def resident_mb() -> int:
    with open("/proc/self/status") as status:
        return int(status.read().split("VmRSS:")[1].split()[0]) // 1024


scenes = int(sys.argv[2]) if len(sys.argv) > 2 else 40
made = point_training.scene_point_data


def measured(*args, **kwargs):
    out = made(*args, **kwargs)
    measured.count += 1
    print(f"scene {measured.count}: {resident_mb()} MB", flush=True)
    return out


measured.count = 0
point_training.scene_point_data = measured
dataset = TransparentSceneDataset(sys.argv[1], "train", views=10)
with tempfile.TemporaryDirectory() as run_dir:
    point_training.prepare_features(dataset, run_dir, PointTrainConfig(net=cpu_config(), max_scenes=scenes),
                                    load_normal_net(shipped_weights(10)[0]))
