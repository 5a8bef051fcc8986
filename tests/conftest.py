"""Shared fixtures: small virtual-bench cameras and grids (seconds to build)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.simulate import BenchConfig, simulate_grid

TINY_SENSOR = (16, 16)
#: Dark level of the DiffuserCam tutorial PSF (mean of its dark corner, ``../shared/data`` README).
CAUSTIC_DARK_LEVEL = 34.0
# CI runs two pytest-xdist workers on two cores. A numerical library that starts a thread per
# core in each worker (and in each CLI or notebook the tests start, which inherit this) spins in
# OpenMP/BLAS waits against the other worker: notebook 04 took 1245 s that way, 134 s with one
# thread each. Set before the workers start, so that their numpy and torch read it at import.
for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

REAL_DATA = Path(os.environ.get("PSFKIT_SHARED_DATA",
                              Path(__file__).resolve().parents[2] / "shared" / "data"))


@pytest.fixture
def fft_counter():
    """Counts of the forward model's FFT calls during the test (:func:`psfkit.forward.count_ffts`,
    the counter ``benchmarks/bench_ekdun_operators.py`` uses): ``fft_counter.take()`` gives
    ``(forward, inverse)`` since the last take (each call transforms all B×C planes)."""
    from psfkit.forward.fft import count_ffts

    with count_ffts() as count:
        yield count


@pytest.fixture(scope="session")
def small_config() -> BenchConfig:
    """The default camera binned 8×: 135 × 180 pixels of 27.6 µm."""
    return BenchConfig(downsample=8)


@pytest.fixture(scope="session")
def grid_3x3(tmp_path_factory: pytest.TempPathFactory, small_config: BenchConfig) -> Path:
    """A simulated 3 × 3 RGB grid with dark frame and ground truth (read-only for tests)."""
    out = tmp_path_factory.mktemp("grids") / "grid_3x3"
    return simulate_grid(out, small_config, grid_shape=(3, 3), progress=False)


@pytest.fixture(scope="session")
def grid_5x5(tmp_path_factory: pytest.TempPathFactory, small_config: BenchConfig) -> Path:
    """A simulated 5 × 5 RGB grid of the default camera binned 8× (strong field variation:
    vignetting, astigmatism, deformation), with ground truth (read-only for tests)."""
    out = tmp_path_factory.mktemp("grids") / "grid_5x5"
    return simulate_grid(out, small_config, grid_shape=(5, 5), progress=False)


@pytest.fixture(scope="session")
def grid_5x5_field_free(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """As :func:`grid_5x5`, of the field-free camera (``BenchConfig(field_free=True)``: every
    PSF the on-axis one translated, no vignetting)."""
    out = tmp_path_factory.mktemp("grids") / "grid_5x5_field_free"
    return simulate_grid(out, BenchConfig(downsample=8, field_free=True), grid_shape=(5, 5),
                         progress=False)


@pytest.fixture(scope="session")
def real_data():
    """``real_data(*parts)``: a path under ``../shared/data`` (or ``$PSFKIT_SHARED_DATA``);
    skips the test, saying why, when the shared data are absent."""

    def locate(*parts: str) -> Path:
        path = REAL_DATA.joinpath(*parts)
        if not path.exists():
            pytest.skip(f"real data not available: {path}")
        return path

    return locate


@pytest.fixture(scope="session")
def real_caustic(real_data) -> np.ndarray:
    """The real DiffuserCam tutorial PSF (1200 × 1600, float64) with its dark level
    :data:`CAUSTIC_DARK_LEVEL` subtracted (not clipped: the noise stays zero-mean)."""
    import tifffile

    psf = tifffile.imread(real_data("diffusercam_tutorial", "psf_sample.tif"))
    return psf.astype(np.float64) - CAUSTIC_DARK_LEVEL


@pytest.fixture()
def torch_one_thread():
    """One intra-op torch thread for the test (tiny tensors: more threads only contend with the
    other pytest-xdist worker); restores the previous count."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def bench_grid_ds2(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 5 × 5 RGB grid binned 2× (540 × 720 px) spanning 80 % of the field of view, with
    realistic noise: fine enough pixels for sub-pixel warp statistics (about 20 s)."""
    out = tmp_path_factory.mktemp("grids") / "grid_5x5_ds2"
    return simulate_grid(out, BenchConfig(downsample=2), grid_shape=(5, 5), extent=0.8,
                         progress=False)


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory) -> tuple[Path, Path]:
    """A pairs folder of 8 dead-leaves scenes measured through a 3-kernel model, and the
    kernel file."""
    import torch

    from ekdun.data.deadleaves import dead_leaves
    from ekdun.physics.operators import EigenKernelOperator
    from research.synthetic import caustic_psf

    root = tmp_path_factory.mktemp("tiny")
    psf = caustic_psf(TINY_SENSOR, 3, seed=3)
    kernels = np.stack([psf, 0.8 * np.roll(psf, 1, axis=1), 0.8 * np.roll(psf, 1, axis=2)])
    kernel_file = save_kernels(root / "k.npz", KernelModel(kernels=kernels,
                                                           sensor_shape=TINY_SENSOR))
    op = EigenKernelOperator.from_kernel_model(load_kernels(kernel_file))
    for sub in ("scene", "measurement"):
        (root / "pairs" / sub).mkdir(parents=True)
    for i in range(8):
        x = torch.as_tensor(dead_leaves(TINY_SENSOR, i))[None]
        with torch.no_grad():
            y = op.A(x)[0].numpy()
        np.save(root / "pairs" / "scene" / f"im{i}.npy", np.moveaxis(x[0].numpy(), 0, -1))
        np.save(root / "pairs" / "measurement" / f"im{i}.npy", np.moveaxis(y, 0, -1))
    return root / "pairs", kernel_file


def _write_pairs_folder(root: Path, scenes: np.ndarray, measurements: np.ndarray) -> Path:
    """A pairs folder (``scene/`` and ``measurement/``, ``imN.npy`` H×W×C) of ``(N, C, H, W)``
    scenes and measurements; returns ``root``."""
    (root / "scene").mkdir(parents=True)
    (root / "measurement").mkdir()
    for i, (x, y) in enumerate(zip(scenes, measurements, strict=True)):
        np.save(root / "scene" / f"im{i}.npy", np.moveaxis(x, 0, -1))
        np.save(root / "measurement" / f"im{i}.npy", np.moveaxis(y, 0, -1))
    return root


@pytest.fixture(scope="session")
def write_pairs():
    """The function that writes a pairs folder (:func:`_write_pairs_folder`)."""
    return _write_pairs_folder
