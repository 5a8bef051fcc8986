"""The one forward model (psfkit.forward): torch-free geometry, the shared FFT counter."""

import subprocess
import sys

import torch

from psfkit.forward import KernelSpaceOperator, count_ffts, kernel_spectra, padded_shape, rfft2


def test_geometry_and_kernel_file_load_without_torch():
    code = ("import sys, psfkit.forward, psfkit.kernelfile; "
            "assert psfkit.forward.padded_shape((3, 5), 2) == (6, 10); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "False"
    assert padded_shape((4, 6), 3) == (12, 18)


def test_count_ffts_counts_every_user_and_nests():
    x = torch.rand(2, 1, 6, 7, dtype=torch.float64)
    with count_ffts() as outer:
        rfft2(x)
        with count_ffts() as inner:
            kernel_spectra(torch.rand(1, 1, 3, 3, dtype=torch.float64), (12, 14))
            # the kernel-space form of fit-pairs: scene spectra once, then 1 + 1 per forward
            op = KernelSpaceOperator(x, "si", "sensor", (6, 7))
            assert inner.take() == (2, 0)
            op.forward(torch.rand(1, 1, 6, 7, dtype=torch.float64))
            assert inner.take() == (1, 1)
    assert outer.as_tuple() == (4, 1)
    rfft2(x)                               # outside every block: not counted
    assert outer.as_tuple() == (4, 1)
