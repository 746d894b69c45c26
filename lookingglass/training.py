"""The training loop the networks share: run folder, schedule, checkpoints, exact resume, metrics,
DistributedDataParallel and progress. A network's trainer supplies only what is its own: how to
build the net and what one step computes (`TrainingSession.fit`'s `build` and `step`).

RUN_DIR holds:
  config.json        the resolved training config (a dataclass, as JSON); a second run in the same
                     folder must bring the same config, else it is refused (LookingGlassError)
  checkpoint.pt      model + optimizer + step + epoch, written atomically every
                     `checkpoint_every` steps and at the end of every epoch; loaded with
                     weights_only=True (never unpickles code)
  metrics.jsonl      one line per epoch: epoch, step, lr, loss, the step's own logged values
                     (means over the epoch), seconds, processes
  weights.safetensors + weights.json   the shipped form: tensors + {"net": the network config,
                     "kind": which network, ...}, written at the end of the run

Schedule: Adam, lr · 0.5^(epoch // lr_halve_epochs) (the paper: 1e-4 halved every 2 epochs).
Each epoch visits the first `max_scenes` items (0: all) in an order drawn from seed + epoch.

Under torchrun (WORLD_SIZE > 1) the process group is opened (nccl on CUDA, gloo on CPU), each
process takes every world-th item of the epoch's order, the order padded by wrapping around as
torch's DistributedSampler does (so every process takes the same number of steps and none waits
forever in an all-reduce), DDP averages the gradients, and only rank 0 writes files and reports.
`step` counts the steps of one process (= optimizer updates).

Exact resume: the schedule, the order and the position in the epoch follow from (seed, step,
epoch) in the checkpoint, so an interrupted run that resumes ends with the weights of an
uninterrupted one, provided `step` itself is deterministic given (model, item, step).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from pathlib import Path
from typing import Any, Callable, Protocol

import torch
import torch.distributed as dist
from torch import Tensor, nn

from .configio import changed_keys
from .errors import LookingGlassError
from .fileio import write_atomic, write_json
from .progress import Reporter
from .weights import check_initial_weights, load_initial_weights, save_weights

__all__ = [
    "Schedule",
    "StepFn",
    "TrainingSession",
    "learning_rate",
    "epoch_order",
    "save_checkpoint",
    "load_checkpoint",
    "dist_info",
    "record_or_compare",
]


class Schedule(Protocol):
    """The fields of a training config that the loop reads (a dataclass; saved as config.json)."""

    epochs: int
    lr: float
    lr_halve_epochs: int
    checkpoint_every: int
    seed: int
    max_scenes: int
    init: str  # weights.safetensors to start from (fine-tuning); "" for a random start
    net: Any  # the network's config dataclass (--init weights must have been made with the same)


class StepFn(Protocol):
    def __call__(self, model: nn.Module, index: int, step: int) -> tuple[Tensor, dict[str, float]]:
        """One training step's forward pass on item `index` at global step `step` (0-based):
        returns the loss to minimize (a scalar with gradients) and extra values to log (floats,
        averaged over the epoch into metrics.jsonl under their own keys). `model` is the net, or
        its DDP wrapper under torchrun: call it, don't reach into it."""
        ...


def learning_rate(config: Schedule, epoch: int) -> float:
    """lr · 0.5^(epoch // lr_halve_epochs); epoch counts from 0."""
    return config.lr * 0.5 ** (epoch // max(1, config.lr_halve_epochs))


def epoch_order(n: int, seed: int, epoch: int, rank: int = 0, world: int = 1) -> list[int]:
    """This process's items of one epoch: a permutation of range(n) drawn from seed + epoch,
    padded by wrapping to a multiple of `world`, every world-th item from `rank` on
    (ceil(n / world) items; the permutation itself when world = 1)."""
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed + epoch)).tolist()
    total = math.ceil(n / world) * world
    while len(order) < total:
        order += order[: total - len(order)]
    return order[rank:total:world]


# ---- files ---------------------------------------------------------------------------------------
def save_checkpoint(path: Path, net: nn.Module, opt: torch.optim.Optimizer, step: int, epoch: int) -> None:
    """Model + optimizer state, the global step and the epoch to resume in, written atomically."""
    state = {"model": net.state_dict(), "optim": opt.state_dict(), "step": step, "epoch": epoch}
    write_atomic(path, lambda tmp: torch.save(state, tmp))


def load_checkpoint(path: Path) -> dict:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a checkpoint is ours, but the user may hand us anything
        raise LookingGlassError(f"cannot read checkpoint ({exc})", path) from None


def dist_info() -> tuple[int, int]:
    """(rank, world size); (0, 1) outside a process group."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


# ---- the session ----------------------------------------------------------------------------------
def record_or_compare(path: Path, data: dict, rank: int, mismatch: str, advice: str) -> None:
    """The first run writes `data` to `path` (rank 0 only); a later one must bring the same data,
    else LookingGlassError("<mismatch> (differs in <keys>); <advice>") naming the file."""
    data = json.loads(json.dumps(data))  # tuples -> lists, as stored
    if path.exists():
        try:
            saved = json.loads(path.read_text())
        except ValueError as exc:
            raise LookingGlassError(f"cannot read {path.name} ({exc})", path) from None
        if saved != data:
            raise LookingGlassError(f"{mismatch} (differs in {', '.join(changed_keys(saved, data))}); {advice}", path)
    elif rank == 0:
        write_json(path, data)


class TrainingSession:
    """One training run in RUN_DIR: opens the process group under torchrun, checks or writes
    config.json, and runs the loop (`fit`). Work a trainer does before the loop (e.g. caching
    inputs) can use `rank` / `world` to split itself and `barrier()` to wait for the others.

    config: a dataclass with the `Schedule` fields and `net`, the network's config (all of it is
    saved and compared).
    device: "cpu", "cuda" or "cuda:N". reporter: progress and messages (rank 0 only).
    """

    def __init__(self, run_dir: str | os.PathLike, config: Schedule, device: str = "cpu",
                 reporter: Reporter | None = None):
        self.run_dir = Path(run_dir)
        self.config = config
        self.device = device
        self.ddp = "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1
        if self.ddp and device == "cuda":  # one GPU per process, as torchrun numbers them on each machine
            self.device = device = f"cuda:{int(os.environ.get('LOCAL_RANK', 0))}"
            torch.cuda.set_device(self.device)
        self.owns_group = self.ddp and not dist.is_initialized()
        if self.owns_group:
            dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
        self.rank, self.world = dist_info()
        self.reporter = reporter or Reporter(quiet=self.rank != 0)
        if self.rank != 0:
            self.reporter = Reporter(quiet=True)
        if config.init:  # before config.json is written: a bad --init must not hold the run folder
            check_initial_weights(config.init, config.net)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._check_config()

    def _check_config(self) -> None:
        record_or_compare(self.run_dir / "config.json", dataclasses.asdict(self.config), self.rank,
                          "run folder holds a different config", "use a new --out or the same settings")

    def barrier(self) -> None:
        """Wait for every process (no-op outside torchrun)."""
        if self.ddp:
            dist.barrier()

    def fit(self, build: Callable[[], nn.Module], num_items: int, step: StepFn,
            weights_extra: Callable[[int], dict] | None = None, labels: dict[str, str] | None = None,
            max_steps: int | None = None) -> dict:
        """Train; resumes from RUN_DIR/checkpoint.pt. Returns the last epoch's metrics.

        build(): the untrained net (called after torch.manual_seed(config.seed); it is moved to
        the session's device). num_items: items per epoch before max_scenes. step: see `StepFn`.
        weights_extra(steps): extra entries for weights.json. labels: names for the logged values
        in the epoch's summary line. max_steps: stop after this global step (as if interrupted:
        the checkpoint lets a later call finish the run).
        """
        config, device, reporter, rank, world = self.config, self.device, self.reporter, self.rank, self.world
        torch.manual_seed(config.seed)
        net = build().to(device)
        opt = torch.optim.Adam(net.parameters(), lr=config.lr)
        done, start_epoch = 0, 0
        ckpt_path = self.run_dir / "checkpoint.pt"
        init_sha = load_initial_weights(net, config.init) if config.init else None
        if init_sha:
            reporter.info(f"starting from {config.init}")
        if ckpt_path.exists():
            ckpt = load_checkpoint(ckpt_path)
            try:
                net.load_state_dict(ckpt["model"])
                opt.load_state_dict(ckpt["optim"])
                done, start_epoch = int(ckpt["step"]), int(ckpt["epoch"])
            except (KeyError, RuntimeError, ValueError) as exc:
                raise LookingGlassError(f"checkpoint does not fit this run ({exc})", ckpt_path) from None
            reporter.info(f"resuming from step {done} (epoch {start_epoch + 1})")
        model = torch.nn.parallel.DistributedDataParallel(net) if self.ddp else net

        n = num_items if not config.max_scenes else min(config.max_scenes, num_items)
        if n < 1:
            raise LookingGlassError("nothing to train on (no items)")
        steps_per_epoch = math.ceil(n / world)
        metrics: dict = {}
        stopped = False
        for epoch in range(start_epoch, config.epochs):
            lr = learning_rate(config, epoch)
            for g in opt.param_groups:
                g["lr"] = lr
            todo = epoch_order(n, config.seed, epoch, rank, world)[done - epoch * steps_per_epoch:]
            losses: list[float] = []
            logs: dict[str, list[float]] = {}
            start = time.perf_counter()
            for index in reporter.track(todo, description=f"epoch {epoch + 1}/{config.epochs}"):
                loss, extra = step(model, index, done)
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(float(loss.detach()))
                for k, v in extra.items():
                    logs.setdefault(k, []).append(float(v))
                done += 1
                if done % config.checkpoint_every == 0 and rank == 0:
                    save_checkpoint(ckpt_path, net, opt, done, epoch)
                if max_steps is not None and done >= max_steps:
                    stopped = True
                    break
            finished = len(losses) == len(todo)
            metrics = {"epoch": epoch + 1, "step": done, "lr": lr, "loss": _mean(losses),
                       **{k: _mean(v) for k, v in logs.items()},
                       "seconds": round(time.perf_counter() - start, 2), "processes": world}
            if rank == 0:
                with open(self.run_dir / "metrics.jsonl", "a") as f:
                    f.write(json.dumps(metrics) + "\n")
                save_checkpoint(ckpt_path, net, opt, done, epoch + 1 if finished else epoch)
                extras = "".join(f", {(labels or {}).get(k, k)} {metrics[k]:.4f}" for k in logs)
                reporter.info(f"epoch {epoch + 1}: loss {metrics['loss']:.4f}{extras} "
                              f"(lr {lr:.1e}, {metrics['seconds']} s)")
            if stopped:
                break
        if rank == 0:
            extra = weights_extra(done) if weights_extra else {"steps": done}
            if init_sha:
                extra["init_sha256"] = init_sha
            save_weights(self.run_dir, net, extra)
        self.barrier()
        if self.owns_group:
            # a process that exits with its gloo group alive can abort at teardown ("terminate
            # called without an active exception", seen once in CI); close it while all wait here
            dist.destroy_process_group()
        return metrics


def _mean(values: list[float]) -> float:
    return sum(values) / max(len(values), 1)
