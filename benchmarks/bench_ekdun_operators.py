"""Benchmark: eigen-kernel operator (3 kernels, sensor side) vs shift-invariant, forward+adjoint.

Target (issue 5): EK forward+adjoint <= 2.1x the SI pair at 1080x1440x3 float32 (2.0 is the
FFT-count limit: 4 + 4 transforms against 1 + 1 + 1 + 1). Both operators use cached kernel
spectra (bound once, as inside the unrolled networks), so only the iterate's FFTs are timed.
The two pairs are timed alternately in one run and the ratio of the medians is printed.

    python benchmarks/bench_ekdun_operators.py                    # paper size, CPU
    python benchmarks/bench_ekdun_operators.py --size 256 256 --device cuda
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from ekdun.physics import EigenKernelOperator, PreparedOperator, ShiftInvariantOperator
from psfkit.forward.fft import count_ffts

# research/ (not installed) holds the synthetic PSF: import it from this checkout
sys.path.append(str(Path(__file__).resolve().parents[1]))
from research.synthetic import caustic_psf


def fft_calls(fn: Callable[[], object]) -> tuple[int, int]:
    """``(forward, inverse)`` 2-D FFT calls of the forward model (:func:`psfkit.forward.count_ffts`,
    the counter the tests use) made by ``fn``."""
    with count_ffts() as count:
        fn()
    return count.as_tuple()


def timed(fn: Callable[[], object], device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, nargs=2, default=(1080, 1440),
                        metavar=("H", "W"), help="sensor size (default 1080 1440)")
    parser.add_argument("--channels", type=int, default=3)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=9)
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    sensor = tuple(args.size)

    psf = torch.as_tensor(caustic_psf(sensor, args.channels), dtype=dtype)
    kernels = torch.stack([psf, torch.roll(psf, 1, dims=-2), torch.roll(psf, 1, dims=-1)])
    si = ShiftInvariantOperator(psf, sensor).to(device)
    ek = EigenKernelOperator.from_basis(kernels, "paper", sensor).to(device)
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(args.batch, args.channels, *sensor, generator=gen, dtype=dtype).to(device)
    y = torch.rand(args.batch, args.channels, *sensor, generator=gen, dtype=dtype).to(device)

    with torch.inference_mode():
        bound: dict[str, PreparedOperator] = {"SI": si.prepare(), "EK": ek.prepare()}

        def pair(op: PreparedOperator) -> Callable[[], object]:
            return lambda: (op.A(x), op.A_adjoint(y))

        for name, op in bound.items():
            fwd, adj = fft_calls(lambda op=op: op.A(x)), fft_calls(lambda op=op: op.A_adjoint(y))
            print(f"{name}: forward {fwd[0]} FFT + {fwd[1]} inverse FFT, adjoint {adj[0]} FFT "
                  f"+ {adj[1]} inverse FFT (each call transforms all {args.batch}x"
                  f"{args.channels} planes)")
        for op in bound.values():                  # warm-up (FFT plans, allocator)
            pair(op)()
            pair(op)()
        times: dict[str, list[float]] = {"SI": [], "EK": []}
        for _ in range(args.repeat):                # alternate to share any drift
            for name, op in bound.items():
                times[name].append(timed(pair(op), device))

    median = {name: statistics.median(t) for name, t in times.items()}
    label = f"{args.batch}x{args.channels}x{sensor[0]}x{sensor[1]} {args.dtype} on {device}"
    if device.type == "cpu":
        label += f" ({torch.get_num_threads()} threads)"
    print(f"forward+adjoint, {label}, median of {args.repeat}:")
    for name in times:
        print(f"  {name}: {median[name] * 1e3:.1f} ms (min {min(times[name]) * 1e3:.1f}, "
              f"max {max(times[name]) * 1e3:.1f})")
    print(f"ratio EK/SI: {median['EK'] / median['SI']:.3f} (target <= 2.1; FFT-count limit "
          "2.0)")


if __name__ == "__main__":
    main()
