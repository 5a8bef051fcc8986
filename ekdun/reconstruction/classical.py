"""Classical reconstruction with a kernel file, as fitted (``ekdun reconstruct K.npz``).

A shift-invariant or eigen-kernel model (either convention) is used exactly as stored: no
clipping of negative values, no per-channel renormalisation (both would change the model).
The solver is the one ADMM-TV, :func:`~ekdun.reconstruction.admm.solve_tv` (the retired
``solver="pdhg"`` runs it with a DeprecationWarning), with the scene on the padded grid.
Images are ``(C, H', W')`` in the model's channel order; files are converted at the boundary.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, InvalidInputError, TensorShapeError
from ekdun.reconstruction.admm import solve_tv
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from psfkit.forward.kernelfile import KernelModel

SOLVERS = ("auto", "admm")
#: Solver names that were removed; they run ADMM (one release, then refused).
RETIRED_SOLVERS = ("pdhg",)
DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass(frozen=True)
class ClassicalOptions:
    """Options of :func:`reconstruct_with_model`.

    Attributes
    ----------
    solver : {"auto", "admm"}
        Both are the one ADMM-TV.
    tv : float
        Relative TV weight (:mod:`ekdun.reconstruction.admm`).
    iterations : int
    nonneg : bool
    tol : float
        Relative-change stopping rule (0 = off).
    dtype : {"float32", "float64"}
    """

    solver: str = "auto"
    tv: float = 3e-4
    iterations: int = 100
    nonneg: bool = True
    tol: float = 0.0
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.solver in RETIRED_SOLVERS:
            warnings.warn(f"solver {self.solver!r} was removed: the ADMM-TV solver runs "
                          "instead", DeprecationWarning, stacklevel=3)
        elif self.solver not in SOLVERS:
            raise ConfigurationError(f"--solver must be one of {', '.join(SOLVERS)}, got "
                                     f"{self.solver!r}")
        if self.dtype not in DTYPES:
            raise ConfigurationError(f"--dtype must be one of {', '.join(DTYPES)}, got "
                                     f"{self.dtype!r}")
        # named as the flags of ekdun reconstruct, never as the fields
        for option, value, low in (("--tv", self.tv, 0), ("--tol", self.tol, 0),
                                   ("--iterations", self.iterations, 1)):
            if value < low:
                raise ConfigurationError(f"{option} must be >= {low}, got {value}")


@dataclass
class ClassicalResult:
    """A reconstruction ``(C, H', W')`` float32 with the solver's iterations and seconds."""

    image: np.ndarray
    iterations: int
    converged: bool
    seconds: float


class ModelReconstructor:
    """A kernel model (used as fitted) ready to reconstruct many measurements: operator,
    spectra and ``‖A‖`` computed once."""

    def __init__(self, model: KernelModel, options: ClassicalOptions | None = None) -> None:
        self.model = model
        self.options = options or ClassicalOptions()
        self.dtype = DTYPES[self.options.dtype]
        self.solver = "admm"
        self.solver_operator = ExtendedSceneOperator.from_kernel_model(model, self.dtype)
        self._norm: float | None = None

    @property
    def sensor_shape(self) -> tuple[int, int]:
        return tuple(self.model.sensor_shape)

    def check(self, measurement: np.ndarray, where: str = "measurement") -> None:
        """Raise :class:`~ekdun.errors.TensorShapeError` unless ``(C, H', W')`` fits the model."""
        c = len(self.model.channels)
        if measurement.ndim != 3 or measurement.shape[0] != c \
                or tuple(measurement.shape[-2:]) != self.sensor_shape:
            got = "x".join(str(s) for s in measurement.shape)
            raise TensorShapeError(
                f"{where}: is {got} (C x H x W) but the kernel model expects {c}x"
                f"{self.sensor_shape[0]}x{self.sensor_shape[1]}")

    def __call__(self, measurement: np.ndarray,
                 callback: Callable[[int, float], None] | None = None) -> ClassicalResult:
        """Reconstruct one ``(C, H', W')`` measurement (the model's channel order)."""
        self.check(measurement)
        o = self.options
        t0 = time.perf_counter()
        with torch.no_grad():
            y = torch.as_tensor(measurement, dtype=self.dtype)
            result = solve_tv(y, self.solver_operator, tv=o.tv, iterations=o.iterations,
                              nonneg=o.nonneg, tol=o.tol, norm=self._norm, callback=callback)
            self._norm = result.operator_norm              # measured once per model
            image = self.solver_operator.crop(result.image[None])[0]
        return ClassicalResult(image.numpy().astype(np.float32), result.iterations,
                               result.converged, time.perf_counter() - t0)


def psf_model(psf: np.ndarray, sensor_shape: tuple[int, int], channels: int | None = None,
              scene_padding: int = 2, where: str = "") -> KernelModel:
    """The shift-invariant kernel model of a PSF ``(C, Hk, Wk)`` or ``(Hk, Wk)`` (centred,
    used as given) for measurements of ``sensor_shape`` with ``channels`` (a mono PSF serves
    each); :class:`TensorShapeError` (naming the file ``where``) when it does not fit them."""
    kernel = np.asarray(psf, dtype=np.float32)
    kernel = kernel[None] if kernel.ndim == 2 else kernel
    name = f"{where}: " if where else ""
    if kernel.ndim != 3:
        raise TensorShapeError(f"{name}a PSF must be (C, H, W) or (H, W), got {kernel.shape}")
    if kernel.shape[-2] > sensor_shape[0] or kernel.shape[-1] > sensor_shape[1]:
        raise TensorShapeError(f"{name}PSF {kernel.shape[-2]}x{kernel.shape[-1]} is larger "
                               f"than the measurement {sensor_shape[0]}x{sensor_shape[1]}")
    if channels is not None and kernel.shape[0] != channels:
        if kernel.shape[0] != 1:
            raise TensorShapeError(f"{name}PSF has {kernel.shape[0]} channels, the "
                                   f"measurement {channels}")
        kernel = np.repeat(kernel, channels, axis=0)
    return KernelModel.shift_invariant(kernel, sensor_shape=tuple(sensor_shape),
                                       scene_padding=scene_padding,
                                       normalization="as given (PSF image)")


_DTYPE_NAMES = {torch.float32: "float32", torch.float64: "float64"}


def admm_tv(measurement: np.ndarray | Tensor, psf: np.ndarray | Tensor, iterations: int = 100,
            tau: float = 1e-3, scene_padding: int = 2, normalize_psf: bool = True,
            dtype: torch.dtype = torch.float64) -> Tensor:
    """ADMM-TV with a shift-invariant PSF (the DiffuserCam tutorial's function, now the
    solver of ``ekdun reconstruct`` through :func:`psf_model`).

    Parameters
    ----------
    measurement : array ``(C, H', W')`` or ``(H', W')``
        Background-subtracted measurement.
    psf : array ``(C, Hk, Wk)`` or ``(Hk, Wk)``
        Centred PSF, at most the measurement's size; a mono PSF serves every channel.
    iterations : int
    tau : float
        TV weight relative to the measurement's peak and ``‖A‖`` (``--tv``).
    scene_padding : int
    normalize_psf : bool
        Scale each PSF channel to unit sum first.
    dtype : torch.float32 or torch.float64

    Returns
    -------
    Tensor
        ``(C, H', W')`` in ``dtype``.
    """
    y = np.asarray(measurement, dtype=np.float64)
    y = y[None] if y.ndim == 2 else y
    h = np.asarray(psf, dtype=np.float64)
    if normalize_psf:
        h = h / np.maximum(h.sum(axis=(-2, -1), keepdims=True), 1e-12)
    model = psf_model(h, y.shape[-2:], y.shape[0], scene_padding)
    options = ClassicalOptions(solver="admm", tv=tau, iterations=iterations,
                               dtype=_DTYPE_NAMES[dtype])
    image = ModelReconstructor(model, options)(y).image
    return torch.as_tensor(image, dtype=dtype)


def reconstruct_with_model(measurement: np.ndarray, model: KernelModel,
                           options: ClassicalOptions | None = None) -> np.ndarray:
    """The ``(C, H', W')`` float32 scene of one measurement (the model's size), in the units
    of ``y = A x``."""
    return ModelReconstructor(model, options)(np.asarray(measurement)).image


def read_classical_measurement(path: str | os.PathLike, channel_order: str = "RGB",
                               downsample: int = 1, background: str = "none",
                               white_level: float | None = None) -> np.ndarray:
    """A measurement file as ``(C, H, W)`` float32 RGB in the toolkit's units, with the mean of
    its ``[5:15, 5:15]`` corner subtracted (``background="corner"``), then box-downsampled."""
    from psfkit.calibration.psf_image import BACKGROUNDS, subtract_background
    from psfkit.io.images import read_image_float
    from psfkit.numerics.resample import bin_mean

    if background not in BACKGROUNDS:
        raise ConfigurationError(f"--background must be none or corner, got {background!r}")
    if downsample < 1:
        raise ConfigurationError(f"--downsample must be >= 1, got {downsample}")
    y = subtract_background(read_image_float(path, channel_order, white_level), background,
                            str(path))
    if downsample > 1:
        if min(y.shape[-2:]) // downsample < 1:   # blame the flag, not an empty image
            raise InvalidInputError(f"--downsample {downsample}: {path} ({y.shape[-2]}x"
                                    f"{y.shape[-1]}) would be binned to no pixel")
        y = bin_mean(y, downsample)
    return np.ascontiguousarray(y, dtype=np.float32)


def reconstruct_folder(model: KernelModel, inputs: Sequence[str | os.PathLike],
                       out_dir: str | os.PathLike, options: ClassicalOptions | None = None,
                       channel_order: str = "RGB", overwrite: bool = False,
                       progress: bool = False, downsample: int = 1,
                       background: str = "none", white_level: float | None = None
                       ) -> list[Path]:
    """Reconstruct measurement files and folders into ``out_dir``, atomically, every input
    read and checked first: ``NAME.npy`` (``H × W × C`` float32 RGB) and an 8-bit
    ``NAME.png`` preview scaled to its maximum."""
    from tqdm.auto import tqdm

    from ekdun.reconstruction.reconstruct import measurement_files
    from psfkit.io.atomic import atomic_directory

    files = measurement_files(inputs)
    recon = ModelReconstructor(model, options)
    images = []
    for f in files:
        y = read_classical_measurement(f, channel_order, downsample, background, white_level)
        recon.check(y, str(f))
        images.append(y)
    written = []
    bar = tqdm(total=len(files), desc="reconstruct", unit="image", disable=not progress)
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        for f, y in zip(files, images, strict=True):
            image = recon(y, callback=_iteration_callback(bar, f.stem) if progress else None).image
            write_reconstruction(tmp / f"{f.stem}.npy", image)
            written.append(Path(out_dir) / f"{f.stem}.npy")
            bar.update(1)
    bar.close()
    return written


def write_reconstruction(path: Path, image: np.ndarray, preview: Path | None = None) -> None:
    """``path`` (``.npy``, ``H × W × C`` float32 RGB) and its ``.png`` preview (default next to
    it), each atomic."""
    from ekdun.reconstruction.reconstruct import to_preview
    from psfkit.io.images import write_image

    if path.suffix != ".npy":
        raise InvalidInputError(f"{path}: the output must be a .npy file")
    write_image(path, np.ascontiguousarray(image, dtype=np.float32))
    write_image(preview if preview is not None else path.with_suffix(".png"),
                to_preview(image / max(float(image.max()), 1e-12)))


def _iteration_callback(bar, name: str) -> Callable[[int, float], None]:
    def show(iteration: int, change: float) -> None:
        if iteration % 10 == 0:
            bar.set_postfix_str(f"{name} it {iteration} Δ {change:.1e}")
    return show
