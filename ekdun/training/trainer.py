"""Training loop: MSE, Adam, ExponentialLR per epoch, atomic checkpoints, resume, DDP, AMP.

:func:`train` writes into ``run_dir``: ``checkpoint.pt`` after every epoch, atomically
(:mod:`ekdun.nets.checkpoint`; ``resume=True`` continues exactly, as the batch order depends
only on ``(seed, epoch)``), ``log.csv`` (one row per epoch) and, for EK-DUN,
``kernels_initial.npz`` / ``kernels_learned.npz`` (psfkit kernel files). The dataset stays on
the device when it fits and the loss is read once per epoch (docs/training.md).
"""

from __future__ import annotations

import os
import random
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import Dataset

from ekdun import device as acc
from ekdun.errors import CheckpointError, ConfigurationError, InvalidInputError
from ekdun.nets.builder import build_network, encode_overrides, seed_kernel_model
from ekdun.nets.checkpoint import load_checkpoint, save_checkpoint
from ekdun.nets.configs import TrainingConfig, get_preset
from ekdun.nets.export import export_kernels
from ekdun.nets.export import initial_kernels as checkpoint_seed
from ekdun.nets.unrolled import UnrolledNetwork
from ekdun.training import distributed as D
from ekdun.training.batches import BatchSource
from ekdun.training.epoch import Loop, train_epoch
from ekdun.training.logs import write_csv_log
from ekdun.training.rng import rng_state, set_rng_state
from ekdun.training.signals import deferred_termination
from psfkit.forward.kernelfile import KernelModel, save_kernels

CHECKPOINT = "checkpoint.pt"
LOG = "log.csv"
KERNELS_INITIAL = "kernels_initial.npz"
KERNELS_LEARNED = "kernels_learned.npz"


@dataclass(frozen=True)
class TrainOptions:
    """Run options; ``None`` takes the preset's :class:`~ekdun.nets.configs.TrainingConfig`.

    ``batch_size`` is the global batch (split over ``torchrun`` processes); ``amp``: see
    :func:`ekdun.device.resolve_amp`; ``channels_last`` ``None``: on CUDA only; ``resident``
    ``None``: keep the dataset on the device when it fits, else stream it with ``workers``;
    ``log_every``: steps between progress-bar loss updates; ``on_epoch``: called with each
    epoch's history row after its checkpoint is written. Hooks for studies (research/):
    ``model_hook`` is called on the built network (e.g. ``EKDUN.use_kernel_module``),
    ``objective`` wraps it into ``(y, x) -> (x̂, extra loss)`` (training minimises MSE + extra,
    the log's ``extra_loss`` its mean) and ``study`` is kept as the metadata's ``study``.
    """

    epochs: int | None = None
    batch_size: int | None = None
    lr: float | None = None
    gamma: float | None = None
    kernel_lr_scale: float | None = None
    seed: int = 0
    amp: bool | str = True
    device: str = "auto"
    progress: bool = True
    threads: int | None = None
    channels_last: bool | None = None
    compile: bool = False
    resident: bool | None = None
    workers: int = 2
    log_every: int = 25
    on_epoch: Callable[[dict[str, Any]], None] | None = None
    #: the ``--config`` run file's record (``psfkit.cli.run_file.run_file_record``), kept in
    #: the checkpoint's metadata
    run_file: dict[str, Any] | None = None
    model_hook: Callable[[UnrolledNetwork], None] | None = None
    objective: Callable[[UnrolledNetwork], nn.Module] | None = None
    study: dict[str, Any] | None = None

    def resolve(self, preset: str, network: str = "ekdun") -> TrainingConfig:
        """The preset's settings for ``network`` (its recipe), replaced by those given."""
        base = get_preset(preset).training_for(network)
        values = {k: getattr(self, k) for k in asdict(base) if getattr(self, k) is not None}
        return replace(base, **values)


def check_training_config(cfg: TrainingConfig) -> None:
    """Refuse out-of-range settings before anything is built or written."""
    for name in ("epochs", "batch_size"):
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigurationError(f"--{name.replace('_', '-')} must be an integer >= 1, "
                                     f"got {value!r}")
    for name in ("lr", "gamma", "kernel_lr_scale"):
        value = float(getattr(cfg, name))
        # kernel_lr_scale 0 freezes the physics kernels, a valid choice
        if not np.isfinite(value) or value < 0 or (value == 0 and name != "kernel_lr_scale"):
            raise ConfigurationError(f"--{name.replace('_', '-')}: must be a finite positive "
                                     f"number, got {value!r}")


def _param_groups(model: nn.Module, lr: float, kernel_lr_scale: float) -> list[dict[str, Any]]:
    # Kernels (free pixels in physics., or a kernel module's kernel_param.) get their own
    # group, times the module's lr_multiplier if it has one.
    kernels, others = [], []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        (kernels if name.startswith(("physics.", "kernel_param.")) else others).append(p)
    groups = [{"params": others, "lr": lr}]
    if kernels:
        multiplier = getattr(getattr(model, "kernel_param", None), "lr_multiplier", 1.0)
        groups.append({"params": kernels, "lr": lr * kernel_lr_scale * multiplier,
                       "name": "kernels"})
    return groups


def make_optimizer(model: nn.Module, cfg: TrainingConfig, device: torch.device
                   ) -> torch.optim.Adam:
    """Adam over the network (lr) and its physics kernels (lr × ``kernel_lr_scale``); fused
    on CUDA (the scaler's inf check then stays on the device)."""
    return torch.optim.Adam(_param_groups(model, cfg.lr, cfg.kernel_lr_scale), lr=cfg.lr,
                            fused=True if device.type == "cuda" else None)


def _check_dataset(dataset: Dataset, model: UnrolledNetwork) -> None:
    if len(dataset) == 0:  # type: ignore[arg-type]
        raise InvalidInputError("the training dataset is empty")
    x, y = dataset[0]
    sensor = tuple(model.physics.sensor_shape)
    if tuple(y.shape[-2:]) != sensor or tuple(x.shape) != tuple(y.shape):
        raise InvalidInputError(
            f"training pairs are {y.shape[-2]}x{y.shape[-1]} but the model's sensor is "
            f"{sensor[0]}x{sensor[1]} (build the model from a kernel file of the data's size)")


def _overlaps(a: Path, b: Path) -> bool:
    """One folder is (inside) the other, after resolving ``..`` and links."""
    a, b = a.resolve(), b.resolve()
    return a == b or a.is_relative_to(b) or b.is_relative_to(a)


def train(run_dir: str | os.PathLike, model_name: str,
          seed: KernelModel | np.ndarray | str | os.PathLike, dataset: Dataset,
          preset: str = "tiny", overrides: dict[str, Any] | None = None,
          options: TrainOptions | None = None, resume: bool = False,
          overwrite: bool = False) -> dict[str, Any]:
    """Train ``model_name`` on ``dataset`` (pairs ``(scene, measurement)``).

    Parameters
    ----------
    run_dir : path-like
    model_name : str
        ``"ekdun"``, ``"le-admm-u"`` or ``"updn"``.
    seed : KernelModel, array or path
        Initial kernels: a kernel file or a measured PSF.
    dataset : torch Dataset
        ``(scene, measurement)`` pairs of ``(C, H', W')`` tensors.
    preset : str
    overrides : dict
        Model configuration fields to change (e.g. ``{"schedule": "base"}``); JSON-able.
    options : TrainOptions
    resume : bool
        Continue from ``run_dir/checkpoint.pt``.
    overwrite : bool
        Start over even if ``run_dir`` holds a checkpoint.

    Returns
    -------
    dict
        ``{"history": [...], "run_dir": str, "parameters": int, "seconds": float}``.
    """
    options = options or TrainOptions()
    cfg = options.resolve(preset, model_name)
    check_training_config(cfg)
    ctx = D.setup(options.device)
    if options.threads:
        torch.set_num_threads(options.threads)
    run_dir = Path(run_dir)
    ckpt_path = run_dir / CHECKPOINT
    overrides = encode_overrides(overrides or {})
    _check_run_folder(run_dir, dataset, resume=resume, overwrite=overwrite)
    # every rank has checked the folder before the main one writes into it (else another
    # rank could find the main rank's first files and refuse alone)
    D.barrier(ctx)
    if cfg.batch_size % ctx.world_size:
        raise ConfigurationError(f"--batch-size {cfg.batch_size} is not divisible by the "
                                 f"{ctx.world_size} processes")

    _seed_everything(options.seed)
    model = build_network(model_name, seed_kernel_model(seed), preset, overrides)
    if options.model_hook is not None:
        options.model_hook(model)
    seed_kernels = model.seed_kernels
    assert seed_kernels is not None       # build_network sets it: what the network starts from
    _check_dataset(dataset, model)
    model.to(ctx.device)
    optimizer = make_optimizer(model, cfg, ctx.device)
    amp = acc.resolve_amp(options.amp, ctx.device)
    loop = Loop(model=model, net=model, optimizer=optimizer,
                 scheduler=torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=cfg.gamma),
                 # Gradient scaling only for fp16 (bf16 has float32's exponent range).
                 scaler=torch.amp.GradScaler("cuda", enabled=amp == "fp16"), amp=amp, ctx=ctx,
                 extra_loss=options.objective is not None)
    channels_last = acc.use_channels_last(options.channels_last, ctx.device)
    if channels_last:
        acc.convolutions_channels_last(model)
    metadata = _run_metadata(model_name, preset, overrides, model, cfg, options, ctx, dataset,
                             amp=amp, channels_last=channels_last)
    initial_kernels = torch.as_tensor(seed_kernels.kernels)
    start_epoch = 1
    if resume:
        doc = load_checkpoint(ckpt_path, map_location=ctx.device)
        initial_kernels, start_epoch = _resume(doc, ckpt_path, loop, metadata, initial_kernels)
        if (model_name == "ekdun" and ctx.is_main
                and not (run_dir / KERNELS_INITIAL).is_file()):
            # a run folder copied with its checkpoint alone (e.g. back from a GPU machine)
            save_kernels(run_dir / KERNELS_INITIAL, checkpoint_seed(doc))
    elif ctx.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        if model_name == "ekdun":
            save_kernels(run_dir / KERNELS_INITIAL, seed_kernels)

    loop.net = _training_module(model, options.objective, ctx, options.compile)
    source = BatchSource(dataset, cfg.batch_size, options.seed, ctx, options.resident,
                         options.workers)
    metadata["resident_dataset"] = source.resident
    started = time.perf_counter()
    for epoch in range(start_epoch, cfg.epochs + 1):
        row = train_epoch(
            loop, source, epoch, cfg.batch_size, metadata, log_every=options.log_every,
            desc=(f"{model_name} epoch {epoch}/{cfg.epochs}"
                  if options.progress and ctx.is_main else None),
            time_compile=options.compile and epoch == start_epoch)
        metadata["history"].append(row)
        metadata["epoch"] = epoch
        if ctx.is_main:
            with deferred_termination():       # the epoch's files agree, even when killed
                _save_epoch(run_dir, model_name, loop, metadata, initial_kernels, options)
        D.barrier(ctx)
    loop.net = model          # the DDP wrapper holds the process group (see D.teardown)
    D.teardown(ctx)
    return {"history": metadata["history"], "run_dir": str(run_dir),
            "parameters": model.parameter_count(),
            "seconds": time.perf_counter() - started, "model": model,
            **({"compile_warmup_s": metadata["compile_warmup_s"]}
               if "compile_warmup_s" in metadata else {})}


def _check_run_folder(run_dir: Path, dataset: Dataset, *, resume: bool,
                      overwrite: bool) -> None:
    """Refuse a folder that cannot be resumed, would be overwritten unasked or holds the data."""
    ckpt_path = run_dir / CHECKPOINT
    if resume and not ckpt_path.is_file():
        raise InvalidInputError(f"{run_dir}: nothing to resume (no {CHECKPOINT})")
    if not resume and ckpt_path.exists() and not overwrite:
        raise InvalidInputError(f"{run_dir}: holds a checkpoint already (use --resume to "
                                "continue or --overwrite to start over)")
    if not resume and not overwrite and run_dir.is_dir() and any(run_dir.iterdir()):
        # the run writes log.csv and kernel files: never over a user's files unasked
        found = sorted(p.name for p in run_dir.iterdir())
        raise InvalidInputError(f"{run_dir}: the run folder is not empty ({', '.join(found[:3])}"
                                f"{', ...' if len(found) > 3 else ''}); choose a new folder or "
                                "use --overwrite to start over in it")
    data_root = getattr(getattr(dataset, "pairs", None), "root", None)   # a PairsDataset's
    if data_root is not None and _overlaps(run_dir, Path(data_root)):
        raise InvalidInputError(f"{run_dir}: the run folder overlaps the training data "
                                f"{data_root}; choose a folder outside it")


def _seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 (global state of user code)
    random.seed(seed)


def _run_metadata(model_name: str, preset: str, overrides: dict[str, Any],
                  model: UnrolledNetwork, cfg: TrainingConfig, options: TrainOptions,
                  ctx: D.DistContext, dataset: Dataset, *, amp: str,
                  channels_last: bool) -> dict[str, Any]:
    """The checkpoint's record of the run (what resume checks, what reconstruct reuses)."""
    assert model.seed_kernels is not None
    return {
        "model": model_name, "preset": preset, "overrides": overrides,
        "schedule": getattr(getattr(model, "config", None), "schedule", None),
        "sensor_shape": list(model.physics.sensor_shape),
        "kernel_metadata": model.seed_kernels.to_metadata(),
        "training": asdict(cfg), "seed": options.seed, "world_size": ctx.world_size,
        "parameters": model.parameter_count(), "amp": amp != "off",
        "precision": amp, "channels_last": channels_last, "compile": options.compile,
        "dataset_size": len(dataset),  # type: ignore[arg-type]
        # how the pairs were read (channel order, binning, held-out names): reconstruct reuses it
        "data": dataset.describe() if hasattr(dataset, "describe") else {},
        "epoch": 0, "history": [],
        **({"run_file": options.run_file} if options.run_file else {}),
        **({"study": options.study} if options.study else {}),
    }


def _resume(doc: dict[str, Any], ckpt_path: Path, loop: Loop, metadata: dict[str, Any],
            initial_kernels: Tensor) -> tuple[Tensor, int]:
    """Load the checkpoint ``doc`` (of the same run settings) into the loop and RNGs, its
    history into ``metadata``; the run's seed kernels and the first epoch still to train."""
    old = doc["metadata"]
    for key in ("model", "preset", "overrides", "sensor_shape", "seed"):
        if old.get(key) != metadata[key]:
            raise CheckpointError(f"{ckpt_path}: was trained with {key}={old.get(key)!r}, "
                                  f"not {metadata[key]!r}; cannot resume")
    loop.model.load_state_dict(doc["model"])
    loop.optimizer.load_state_dict(doc["optimizer"])
    loop.scheduler.load_state_dict(doc["scheduler"])
    if "scaler" in doc and loop.scaler.is_enabled():
        loop.scaler.load_state_dict(doc["scaler"])
    set_rng_state(doc["rng"])
    if "initial_kernels" in doc:        # the run's own seed, whatever file this call names
        initial_kernels = doc["initial_kernels"].cpu()
    metadata["history"] = old.get("history", [])
    metadata["epoch"] = int(old.get("epoch", 0))
    return initial_kernels, int(old.get("epoch", 0)) + 1


def _training_module(model: UnrolledNetwork,
                     objective: Callable[[UnrolledNetwork], nn.Module] | None,
                     ctx: D.DistContext, compile_net: bool) -> nn.Module:
    """The module the steps call: the network (with an objective: network and extra loss in
    one forward pass), wrapped in DDP across processes, compiled on request."""
    net: nn.Module = model if objective is None else objective(model)
    if ctx.distributed:
        net = nn.parallel.DistributedDataParallel(
            net, device_ids=[ctx.device.index] if ctx.device.type == "cuda" else None,
            find_unused_parameters=True)
    if compile_net:
        net = torch.compile(net)
    return net


def _save_epoch(run_dir: Path, model_name: str, loop: Loop, metadata: dict[str, Any],
                initial_kernels: Tensor, options: TrainOptions) -> None:
    """The epoch's checkpoint (atomic), log and, for EK-DUN, learned kernel file."""
    if getattr(loop.model, "kernel_param", None) is not None:
        loop.model.sync_kernels()     # physics.kernels: what a kernel module makes now
    save_checkpoint(run_dir / CHECKPOINT, {
        "metadata": metadata, "model": loop.model.state_dict(),
        "initial_kernels": initial_kernels,
        "optimizer": loop.optimizer.state_dict(), "scheduler": loop.scheduler.state_dict(),
        "scaler": loop.scaler.state_dict(), "rng": rng_state()})
    write_csv_log(run_dir / LOG, metadata["history"])
    if model_name == "ekdun":
        learned = export_kernels(loop.model)
        learned = replace(learned, provenance={**learned.provenance, "epoch": metadata["epoch"]})
        save_kernels(run_dir / KERNELS_LEARNED, learned)
    if options.on_epoch is not None:
        options.on_epoch(metadata["history"][-1])
