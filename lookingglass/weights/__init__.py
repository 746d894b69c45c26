"""Network weights: saving, loading and the shipped files, in one place for inference and training.

A weights file is `NAME.safetensors` (tensors only: never unpickled) with `NAME.json` beside it:
{"net": the network's config dataclass as a dict, "kind": "normals" | "points" | "ior", ...provenance}.
The packaged weights live in this folder as `{kind}_{VV}views.safetensors`, one pair per trained
view count; `shipped_weights` picks the nearest.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from safetensors.torch import load_file, save_file
from torch import nn

from ..configio import changed_keys, config_from_dict
from ..errors import LookingGlassError
from ..fileio import read_json, sha256_file, write_atomic, write_json

WEIGHTS_DIR = Path(__file__).resolve().parent
TRAINED_VIEWS = (5, 10, 20)
# Weights made before the trainers recorded it were all trained on the cpu dataset preset's maps.
DEFAULT_ENVMAP_HEIGHT = 128


def shipped_weights(num_views: int, kind: str = "normals") -> tuple[Path | None, int]:
    """The packaged weights of `kind` ("normals", "points" or "ior") for the trained view count nearest
    `num_views` (ties: the larger count), and that count; (None, 0) if none ship."""
    available = [v for v in TRAINED_VIEWS if (WEIGHTS_DIR / f"{kind}_{v:02d}views.safetensors").exists()]
    if not available:
        return None, 0
    best = min(available, key=lambda v: (abs(v - num_views), -v))
    return WEIGHTS_DIR / f"{kind}_{best:02d}views.safetensors", best


def save_weights(run_dir: str | os.PathLike, net: nn.Module, extra: dict | None = None) -> Path:
    """RUN_DIR/weights.safetensors + weights.json ({"net": asdict(net.cfg), **extra}), atomically.
    `net.cfg` is the network's config dataclass."""
    run_dir = Path(run_dir)
    state = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    write_atomic(run_dir / "weights.safetensors", lambda tmp: save_file(state, str(tmp)))
    write_json(run_dir / "weights.json", {"net": dataclasses.asdict(net.cfg), **(extra or {})})
    return run_dir / "weights.safetensors"


def read_weights_config(path: str | os.PathLike) -> dict:
    """The JSON beside weights file `path`, checked to hold a "net" entry."""
    path = Path(path)
    meta_path = path.with_suffix(".json")
    if path.is_dir():
        raise LookingGlassError("weights must be a .safetensors file, not a folder", path)
    if not path.exists():
        raise LookingGlassError("weights file not found", path)
    if not meta_path.exists():
        raise LookingGlassError("network config not found beside the weights", meta_path)
    meta = read_json(meta_path, "network config")
    if not isinstance(meta, dict) or "net" not in meta:
        raise LookingGlassError('network config has no "net" entry', meta_path)
    return meta


def load_weights(path: str | os.PathLike, config_cls: type, net_cls: Callable[[Any], nn.Module],
                 kind: str | None = None) -> tuple[nn.Module, dict]:
    """A net from weights.safetensors and the weights.json beside it (never unpickles).

    config_cls: the network's config dataclass; net_cls(cfg) builds the net. kind: when given and
    weights.json names a different "kind", refuse (e.g. point-net weights handed to the normal
    net); files without a "kind" are accepted. Returns (net in eval mode on the CPU, the JSON).
    """
    path = Path(path)
    meta = read_weights_config(path)
    if kind is not None and meta.get("kind", kind) != kind:
        raise LookingGlassError(f"these are {meta['kind']}-network weights, not {kind}-network ones", path)
    cfg = config_from_dict(config_cls, meta["net"], where=str(path.with_suffix(".json")))
    net = net_cls(cfg)
    try:
        net.load_state_dict(load_file(str(path)))
    except Exception as exc:  # a user's file: any failure to fit is a clear error, not a traceback
        raise LookingGlassError(f"weights do not fit the network config ({exc})", path) from None
    return net.eval(), meta


@dataclass
class NormalWeights:
    """The normal network ready for inference. envmap_height: the environment-map height its
    rendering layer and cost volume were trained with (the capture's map is resized to it)."""

    net: Any  # NormalNet (imported lazily: this module is imported by the networks' trainers)
    path: Path
    envmap_height: int


@dataclass
class PointWeights:
    """The point network ready for inference. strategy: the feature mapping it was trained on."""

    net: Any  # PointNet
    path: Path
    strategy: str


def load_normal_net(path: str | os.PathLike) -> NormalWeights:
    """NNet from its weights file (eval mode, CPU); refuses point-network weights."""
    from ..normals.model import NormalNet, NormalNetConfig

    net, meta = load_weights(path, NormalNetConfig, NormalNet, kind="normals")
    return NormalWeights(net, Path(path), int(meta.get("envmap_height", DEFAULT_ENVMAP_HEIGHT)))


def load_point_net(path: str | os.PathLike) -> PointWeights:
    """PNet from its weights file (eval mode, CPU); refuses normal-network weights."""
    from ..points.model import PointNet, PointNetConfig

    net, meta = load_weights(path, PointNetConfig, PointNet, kind="points")
    return PointWeights(net, Path(path), str(meta.get("strategy", "RE")).upper())


def check_initial_weights(path: str | os.PathLike, net_config: Any) -> dict:
    """Refuse --init weights that are missing or made for another network config (checked
    before a trainer spends time on anything else). Keys the config class lists in
    `FINE_TUNE_FREE` (settings that change no parameter, e.g. the normal net's view count) may
    differ: such weights start the new run, which keeps its own setting. Keys in
    `FINE_TUNE_WIDEN` (input widths) may grow, never shrink: the net's `widen_initial_state`
    fits the weights (load_initial_weights). Returns the saved network config (weights.json "net")."""
    path = Path(path)
    meta_path = path.with_suffix(".json")
    for p in (path, meta_path):
        if not p.exists():
            raise LookingGlassError("--init weights not found" if p == path else
                                    "network config not found beside the --init weights", p)
    try:
        saved = json.loads(meta_path.read_text()).get("net") or {}
    except (ValueError, AttributeError) as exc:
        raise LookingGlassError(f"cannot read the network config ({exc})", meta_path) from None
    wanted = json.loads(json.dumps(dataclasses.asdict(net_config)))
    free = getattr(type(net_config), "FINE_TUNE_FREE", frozenset())
    widen = getattr(type(net_config), "FINE_TUNE_WIDEN", frozenset())
    changed = [k for k in changed_keys(saved, wanted)
               if k not in free and not (k in widen and int(saved.get(k) or 0) <= int(wanted[k]))]
    if changed:
        raise LookingGlassError(f"the --init weights are for another network (differs in "
                                f"{', '.join(changed)})", meta_path)
    return saved


def load_initial_weights(net: nn.Module, path: str | os.PathLike) -> str:
    """Load --init weights into `net` (checked first); returns the file's SHA-256, which the new
    weights.json records."""
    saved = check_initial_weights(path, net.cfg)
    try:
        state = load_file(str(path))
        if hasattr(net, "widen_initial_state"):
            state = net.widen_initial_state(state, saved)
        net.load_state_dict(state)
    except Exception as exc:
        raise LookingGlassError(f"cannot load the --init weights ({exc})", path) from None
    return sha256_file(path)
