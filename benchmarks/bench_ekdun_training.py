"""Benchmark: ``ekdun train``'s throughput against the bare model step (issue 15).

In one run, alternating epoch by epoch (so that a change of load on a shared machine hits
both alike):

bare step
    forward, MSE loss, backward and Adam step of the network on a batch already on the device
    (the same network, parameter groups, batch, precision and memory format as the trainer):
    the model's own speed.
trainer
    :func:`ekdun.training.train` (the library entry point of ``ekdun train``) on an in-memory
    dataset; the steady-state time of epoch ``k >= 2`` is the wall time from the end of epoch
    ``k - 1`` to the end of epoch ``k``, including everything the loop does between steps and
    epochs (batches, checkpoints, logs, kernel export), but not the start-up or the first
    epoch (warm-up, compilation).

After each trainer epoch (in the trainer's ``on_epoch`` callback, whose time is taken out of
the trainer's) the bare step runs as many steps as an epoch has. ``--repeat`` trainer runs of
``--epochs`` epochs give ``repeat × (epochs − 1)`` (trainer epoch, bare block) pairs; the table
gives the median images/s of each and the median of the per-pair ratios trainer / bare
(target >= 0.9), from wall-clock time and, on CPU, from the process's CPU time (less
sensitive to other processes on a shared machine).

    python benchmarks/bench_ekdun_training.py                               # tiny, CPU
    python benchmarks/bench_ekdun_training.py --amp bf16                    # bf16 autocast
    python benchmarks/bench_ekdun_training.py --preset paper --size 256 256 --batch 8 --amp fp16
    python benchmarks/bench_ekdun_training.py --preset paper --batch 1 --n-train 8   # paper size

With ``--compile`` the bare network is compiled first (its warm-up is printed); the trainer's
networks then find the compiled code in the process's caches, so their reported warm-up is
shorter than a fresh ``ekdun train --compile`` would see.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ekdun import device as acc
from ekdun.nets.builder import build_network
from ekdun.nets.configs import get_preset
from ekdun.physics.operators import EigenKernelOperator
from ekdun.training import TrainOptions, train
from ekdun.training.trainer import make_optimizer
from psfkit.forward.kernelfile import KernelModel

# research/ (not installed) holds the synthetic PSF: import it from this checkout
sys.path.append(str(Path(__file__).resolve().parents[1]))
from research.synthetic import caustic_psf


def seed_model(sensor: tuple[int, int]) -> KernelModel:
    """A 3-kernel (paper basis) model from a synthetic caustic PSF."""
    psf = caustic_psf(sensor, 3, seed=3)
    kernels = np.stack([psf, 0.8 * np.roll(psf, 1, axis=1), 0.8 * np.roll(psf, 1, axis=2)])
    return KernelModel(kernels=kernels.astype(np.float32), sensor_shape=sensor)


class PairsInMemory(torch.utils.data.Dataset):
    """Random scenes and their measurements through the seed model, ``(C, H', W')`` each."""

    def __init__(self, seed: KernelModel, n: int) -> None:
        gen = torch.Generator().manual_seed(0)
        self.x = torch.rand(n, len(seed.channels), *seed.sensor_shape, generator=gen)
        op = EigenKernelOperator.from_kernel_model(seed)
        with torch.no_grad():
            self.y = torch.cat([op.A(self.x[i:i + 4]) for i in range(0, n, 4)])

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.x[i], self.y[i]


class BareStep:
    """The network's training step on one fixed batch on the device."""

    def __init__(self, args: argparse.Namespace, seed: KernelModel, data: PairsInMemory,
                 device: torch.device, amp: str, channels_last: bool) -> None:
        cfg = get_preset(args.preset).training
        self.model = build_network(args.model, seed, args.preset, args.overrides).to(device)
        if channels_last:
            acc.convolutions_channels_last(self.model)
        self.net = torch.compile(self.model) if args.compile else self.model
        self.optimizer = make_optimizer(self.model, cfg, device)
        self.scaler = torch.amp.GradScaler("cuda", enabled=amp == "fp16")
        self.x = data.x[:args.batch].to(device)
        self.y = data.y[:args.batch].to(device)
        self.amp, self.device = amp, device

    def step(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        with acc.autocast(self.amp, self.device):
            out = self.net(self.y)
        loss = nn.functional.mse_loss(out.float(), self.x)
        self.scaler.scale(loss).backward()
        self.scaler.step(self.optimizer)
        self.scaler.update()

    def seconds(self, steps: int) -> tuple[float, float]:
        """Wall and CPU seconds of ``steps`` steps."""
        acc.cuda_synchronize(self.device)
        wall, cpu = time.perf_counter(), time.process_time()
        for _ in range(steps):
            self.step()
        acc.cuda_synchronize(self.device)
        return time.perf_counter() - wall, time.process_time() - cpu


def one_round(args: argparse.Namespace, seed: KernelModel, data: PairsInMemory, amp: str,
              bare: BareStep) -> tuple[list[tuple[float, float, float, float]], float | None]:
    """One trainer run with a bare block after each epoch.

    Returns ``[(trainer wall, trainer cpu, bare wall, bare cpu) seconds per epoch 2..E]`` and
    the trainer's compile warm-up.
    """
    steps = len(data) // args.batch
    marks: list[tuple[float, float, float, float]] = []   # (wall in, cpu in, wall out, cpu out)
    blocks: list[tuple[float, float]] = []

    def between_epochs(_row: dict) -> None:
        wall_in, cpu_in = time.perf_counter(), time.process_time()
        blocks.append(bare.seconds(steps))
        marks.append((wall_in, cpu_in, time.perf_counter(), time.process_time()))

    options = TrainOptions(epochs=args.epochs, batch_size=args.batch, seed=0, amp=amp,
                           device=args.device, progress=False, threads=args.threads or None,
                           channels_last=args.channels_last, compile=args.compile,
                           on_epoch=between_epochs)
    with tempfile.TemporaryDirectory() as tmp:
        result = train(Path(tmp) / "run", args.model, seed, data, args.preset,
                       args.overrides, options)
    pairs = [(marks[k][0] - marks[k - 1][2], marks[k][1] - marks[k - 1][3], *blocks[k])
             for k in range(1, len(marks))]
    return pairs, result.get("compile_warmup_s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="tiny", choices=("tiny", "paper"))
    parser.add_argument("--size", type=int, nargs=2, metavar=("H", "W"),
                        help="sensor size (default: the preset's, 64x64 tiny, 1080x1440 paper)")
    parser.add_argument("--batch", type=int, help="batch size (default: the preset's, 4)")
    parser.add_argument("--model", default="ekdun", choices=("ekdun", "le-admm-u", "updn"))
    parser.add_argument("--schedule", default="last-2", help="EK-DUN schedule")
    parser.add_argument("--n-train", type=int, default=48, help="pairs in the dataset")
    parser.add_argument("--epochs", type=int, default=3,
                        help="trainer epochs per round (the first is warm-up)")
    parser.add_argument("--repeat", type=int, default=3, help="alternating rounds")
    parser.add_argument("--device", default="auto", help="auto (cuda if present), cpu, cuda")
    parser.add_argument("--amp", default="off", choices=acc.AMP_CHOICES)
    parser.add_argument("--channels-last", action=argparse.BooleanOptionalAction,
                        default=None, help="default: on CUDA only")
    parser.add_argument("--compile", action="store_true", help="torch.compile both")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (0: default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(args.device)
    preset = get_preset(args.preset)
    sensor = tuple(args.size) if args.size else tuple(preset.sensor_shape)
    args.batch = args.batch or preset.training.batch_size
    args.overrides = {"schedule": args.schedule} if args.model == "ekdun" else {}
    amp = acc.resolve_amp(args.amp, device)
    channels_last = acc.use_channels_last(args.channels_last, device)
    seed = seed_model(sensor)
    data = PairsInMemory(seed, args.n_train)
    bare = BareStep(args, seed, data, device, amp, channels_last)
    warm = time.perf_counter()
    for _ in range(3):
        bare.step()
    acc.cuda_synchronize(device)
    bare_warmup = time.perf_counter() - warm
    print(f"{args.model} ({args.schedule}) preset {args.preset}, {sensor[0]}x{sensor[1]}, "
          f"batch {args.batch}, {args.n_train} pairs, device {device}, amp {amp}, "
          f"channels_last {channels_last}, compile {args.compile}, "
          f"threads {torch.get_num_threads()}; bare warm-up (3 steps) {bare_warmup:.1f} s",
          flush=True)
    images = (len(data) // args.batch) * args.batch      # per epoch
    rows: list[tuple[float, float, float, float]] = []
    for r in range(args.repeat):
        pairs, warmup = one_round(args, seed, data, amp, bare)
        rows.extend(pairs)
        extra = f"; trainer compile warm-up {warmup:.1f} s" if warmup is not None else ""
        print(f"  run {r + 1}: " + ", ".join(
            f"trainer {images / tw:.2f} / bare {images / bw:.2f} img/s"
            for tw, _tc, bw, _bc in pairs) + extra, flush=True)
    cpu = device.type == "cpu"
    n = len(rows)
    print(f"\n| measure (median of {n} epoch pairs) | wall img/s |"
          + (" CPU-time img/s |" if cpu else ""))
    print("| --- | --- |" + (" --- |" if cpu else ""))
    for label, i in (("bare step (forward, loss, backward, Adam)", 2),
                     (f"ekdun train, steady state (epochs 2..{args.epochs})", 0)):
        line = f"| {label} | {statistics.median(images / row[i] for row in rows):.2f} |"
        if cpu:
            line += f" {statistics.median(images / row[i + 1] for row in rows):.2f} |"
        print(line)
    line = ("| ratio trainer / bare (target >= 0.9) | "
            f"{statistics.median(row[2] / row[0] for row in rows):.3f} |")
    if cpu:
        line += f" {statistics.median(row[3] / row[1] for row in rows):.3f} |"
    print(line)


if __name__ == "__main__":
    main()
