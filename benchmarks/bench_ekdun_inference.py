"""Benchmark: inference time and peak memory of EK-DUN (3 schedules), Le-ADMM-U and UPDN.

Targets (issue 5, paper size 1080x1440x3, batch 1): EK-DUN last-2 <= 1.05x EK-DUN base-only
(paper: 1.03x) and <= 0.75x UPDN (paper: 0.187 s vs 0.257 s on an A100).

All models are built from one synthetic caustic PSF with the preset's architectures and run
under ``torch.inference_mode()``, in one run of this script:

1. Peak memory: each model in a fresh subprocess runs one inference. On CPU the peak is the
   resident-set high-water mark (``VmHWM``, reset through ``/proc/self/clear_refs`` just
   before the inference, so it covers the inference alone; ``ru_maxrss`` where the reset is
   unavailable), reported as the increase over the resident set before the inference and as
   the absolute peak; on CUDA ``torch.cuda.max_memory_allocated``.
2. Time: one fresh subprocess builds all models, runs one warm-up inference of each, then
   ``--repeat`` rounds in which every model runs once (round-robin, so that a change of load
   on the machine hits all models alike); the median per model and the ratios are printed.

    python benchmarks/bench_ekdun_inference.py                      # paper size, CPU
    python benchmarks/bench_ekdun_inference.py --size 256 320       # smaller
    python benchmarks/bench_ekdun_inference.py --device cuda
    python benchmarks/bench_ekdun_inference.py --device cuda --amp fp16   # also fp16 autocast

With ``--amp bf16|fp16`` the time child also runs every model under autocast (round-robin
with the float32 runs) and reports the speed-up and the PSNR change: the input is a
dead-leaves scene imaged through the PSF the models are built from, and the PSNR of the
autocast output against that scene is compared with the float32 output's (plus the PSNR of the
autocast output against the float32 output itself). Untrained networks start with
zero-initialised U-Net outputs, so their autocast outputs equal float32's; a trained network
is measured with ``--checkpoint run/checkpoint.pt --pairs PAIRS`` (its first pair is the
input and the ground truth; the size is the checkpoint's):

    python benchmarks/bench_ekdun_inference.py --checkpoint runs/ek/checkpoint.pt \
        --pairs data/test --amp bf16 --threads 1
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

# research/ (not installed) holds the synthetic PSF: import it from this checkout
sys.path.append(str(Path(__file__).resolve().parents[1]))

MODELS = {  # label: (model name, configuration overrides)
    "ekdun-base": ("ekdun", {"schedule": "base"}),
    "ekdun-last-2": ("ekdun", {"schedule": "last-k", "eigen_last": 2}),
    "ekdun-all": ("ekdun", {"schedule": "all"}),
    "le-admm-u": ("le-admm-u", {}),
    "updn": ("updn", {}),
}


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _reset_peak_rss() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _peak_rss_bytes(reset_worked: bool) -> int:
    if reset_worked:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _scene_and_measurement(args: argparse.Namespace):
    """A dead-leaves scene ``(1, 3, H, W)`` and its measurement through the models' PSF."""
    import torch

    from ekdun.data.deadleaves import dead_leaves
    from ekdun.physics.operators import ShiftInvariantOperator
    from research.synthetic import caustic_psf

    if args.pairs:
        from ekdun.data.pairs import PairsDataset

        x, y = PairsDataset(args.pairs, preload=False)[0]
        return x[None], y[None]
    sensor = tuple(args.size)
    x = torch.as_tensor(dead_leaves(sensor, 0), dtype=torch.float32)[None]
    op = ShiftInvariantOperator.from_psf(caustic_psf(sensor, 3, seed=0))
    with torch.no_grad():
        return x, op.A(x)


def _build(label: str, args: argparse.Namespace, amp: str = "off"
           ) -> tuple[Callable[[], object], int]:
    """``(inference closure returning the output, parameter count)`` of model ``label``."""
    import torch

    from ekdun import device as acc
    from ekdun.nets import build_model
    from research.synthetic import caustic_psf

    device = torch.device(args.device)
    if label == "checkpoint":
        from ekdun.nets.builder import network_from_checkpoint

        model = network_from_checkpoint(args.checkpoint)[0]
    else:
        name, overrides = MODELS[label]
        model = build_model(name, caustic_psf(tuple(args.size), 3, seed=0), args.preset,
                            **overrides)
    model = model.to(device).eval()
    y = _scene_and_measurement(args)[1].to(device)

    def infer() -> object:
        with torch.inference_mode(), acc.autocast(amp, device):   # the resolved amp
            out = model(y)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return out

    return infer, model.parameter_count()


def measure_memory(args: argparse.Namespace) -> None:
    """Child: one inference of ``args.child``, its peak memory and time (JSON line)."""
    import torch

    device = torch.device(args.device)
    infer, params = _build(args.child, args)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        before = torch.cuda.memory_allocated(device)
        start = time.perf_counter()
        infer()
        seconds = time.perf_counter() - start
        peak, kind = torch.cuda.max_memory_allocated(device), "cuda max_memory_allocated"
    else:
        before = _rss_bytes()
        reset = _reset_peak_rss()
        start = time.perf_counter()
        infer()
        seconds = time.perf_counter() - start
        peak = _peak_rss_bytes(reset)
        kind = "VmHWM after clear_refs" if reset else "ru_maxrss"
    print(json.dumps({"model": args.child, "params": params, "first_s": seconds,
                      "peak_increase_gib": (peak - before) / 2**30, "peak_gib": peak / 2**30,
                      "memory_kind": kind}))


def measure_times(args: argparse.Namespace) -> None:
    """Child: all models, warm-up, then round-robin timing (JSON line)."""
    import torch

    from ekdun.evaluation.metrics import psnr

    closures = {label: _build(label, args)[0] for label in args.models}
    quality = {}
    if args.amp != "off":
        x = _scene_and_measurement(args)[0]
        for label in args.models:
            closures[f"{label}+{args.amp}"] = amp_infer = _build(label, args, args.amp)[0]
            ref, low = closures[label]().float().cpu(), amp_infer().float().cpu()
            quality[label] = {"psnr_fp32_db": float(psnr(ref.clamp(0, 1), x)[0]),
                              "psnr_amp_db": float(psnr(low.clamp(0, 1), x)[0]),
                              "psnr_amp_vs_fp32_db": float(psnr(low, ref)[0])}
    for infer in closures.values():
        infer()
    times: dict[str, list[float]] = {label: [] for label in closures}
    for _ in range(args.repeat):
        for label, infer in closures.items():
            start = time.perf_counter()
            infer()
            times[label].append(time.perf_counter() - start)
    print(json.dumps({"times_s": times, "threads": torch.get_num_threads(),
                      "quality": quality}))


def _child(args: argparse.Namespace, role: str, label: str = "") -> dict:
    cmd = [sys.executable, os.path.abspath(__file__), "--role", role, "--child", label,
           "--size", *map(str, args.size), "--preset", args.preset, "--models", *args.models,
           "--repeat", str(args.repeat), "--device", args.device, "--threads", str(args.threads),
           "--amp", args.amp, *(["--checkpoint", args.checkpoint, "--pairs", args.pairs]
                                 if args.checkpoint else [])]
    env = dict(os.environ)
    if args.threads:
        env["OMP_NUM_THREADS"] = str(args.threads)
    proc = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, nargs=2, default=(1080, 1440), metavar=("H", "W"),
                        help="sensor size (default 1080 1440, the paper's)")
    parser.add_argument("--preset", default="paper", help="architecture preset (paper, tiny)")
    parser.add_argument("--models", nargs="+", default=list(MODELS),
                        choices=[*MODELS, "checkpoint"])
    parser.add_argument("--repeat", type=int, default=3, help="timed rounds")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")
    parser.add_argument("--amp", default="off", choices=("off", "bf16", "fp16"),
                        help="also time every model under this autocast (fp16: CUDA)")
    parser.add_argument("--checkpoint", help="time this trained network instead")
    parser.add_argument("--pairs", help="pairs folder for --checkpoint (first pair)")
    parser.add_argument("--role", choices=("memory", "time"), help=argparse.SUPPRESS)
    parser.add_argument("--child", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.checkpoint:
        if not args.pairs:
            parser.error("--checkpoint needs --pairs")
        from ekdun.data.pairs import PairsDataset

        args.models = ["checkpoint"]
        args.size = PairsDataset(args.pairs, preload=False).image_shape[1:]
    if args.role is not None:
        import torch

        if args.threads:
            torch.set_num_threads(args.threads)
        (measure_memory if args.role == "memory" else measure_times)(args)
        return

    h, w = args.size
    what = f"checkpoint {args.checkpoint}" if args.checkpoint else f"preset {args.preset}"
    amp = f" (and {args.amp} autocast)" if args.amp != "off" else ""
    print(f"inference 1x3x{h}x{w} float32{amp}, {what}, device {args.device}", flush=True)
    print("peak memory (one inference per fresh process):", flush=True)
    for label in args.models:
        res = _child(args, "memory", label)
        print(f"  {label:13s} peak +{res['peak_increase_gib']:.2f} GiB over the resident set "
              f"before the inference (absolute {res['peak_gib']:.2f} GiB, "
              f"{res['memory_kind']}); that inference took {res['first_s']:.3f} s; "
              f"{res['params']:,} parameters", flush=True)
    timing = _child(args, "time")
    where = f" ({timing['threads']} threads)" if args.device == "cpu" else ""
    print(f"time, median of {args.repeat} round-robin rounds after one warm-up{where}:")
    median = {}
    for label, runs in timing["times_s"].items():
        median[label] = statistics.median(runs)
        print(f"  {label:18s} {median[label]:8.3f} s  (runs "
              f"{', '.join(f'{t:.3f}' for t in runs)})")
    for label, q in timing.get("quality", {}).items():
        amp_label = f"{label}+{args.amp}"
        print(f"  {amp_label:18s} speed-up {median[label] / median[amp_label]:.2f}x; PSNR vs "
              f"scene {q['psnr_amp_db']:.3f} dB ({args.amp}) vs {q['psnr_fp32_db']:.3f} dB "
              f"(fp32): {q['psnr_amp_db'] - q['psnr_fp32_db']:+.4f} dB; {args.amp} vs fp32 "
              f"output {q['psnr_amp_vs_fp32_db']:.1f} dB")
    if "ekdun-last-2" in median and "ekdun-base" in median:
        print(f"ratio last-2/base: {median['ekdun-last-2'] / median['ekdun-base']:.3f} "
              "(target <= 1.05; paper 1.03)")
    if "ekdun-all" in median and "ekdun-base" in median:
        print(f"ratio all/base:    {median['ekdun-all'] / median['ekdun-base']:.3f} "
              "(paper 1.36)")
    if "ekdun-last-2" in median and "updn" in median:
        print(f"ratio last-2/UPDN: {median['ekdun-last-2'] / median['updn']:.3f} "
              "(target <= 0.75; paper 0.73)")


if __name__ == "__main__":
    main()
