"""The kernel file: the hand-off between measuring (psfkit) and learning (ekdun).

One ``.npz`` file (NumPy, no pickles) holds

``kernels``
    float32 ``(K, C, Hk, Wk)``: the K kernels of the model in the order of the weight basis'
    ``kernel_names`` (``base, v, h`` for the paper), C channels (RGB or L), each stored with
    its origin at the array centre ``(Hk//2, Wk//2)``, the way a PSF image looks.
``metadata``
    a JSON string: ``format`` (``"ekdun-kernels"``), ``version``, ``basis`` (weight basis name,
    see :mod:`psfkit.weights`), ``convention`` (``"sensor"``: weights multiply each kernel's
    image on the sensor, Eq. 7; ``"source"``: weights multiply the scene before each
    convolution), ``kernel_names``, ``channels``, ``sensor_shape`` ``[H', W']`` (measurement
    size, and the grid on which the weights are defined), ``optical_center`` ``[v_c, u_c]``,
    ``scene_padding`` (the convolution runs on a ``scene_padding × sensor_shape`` grid),
    ``normalization`` (how the kernels were scaled), and free-form ``provenance``.

Forward model (``shared/design.md``), scene ``x`` and measurement ``y`` both ``H' × W'``:
``y = Σ_k W_k ⊙ crop(K_k * pad(x))`` for the sensor-side convention and
``y = crop(Σ_k K_k * pad(W_k ⊙ x))`` for the source-side one, where ``pad`` zero-fills ``x`` into
the centre of the padded grid and ``crop`` keeps its central ``H' × W'``. A kernel is at most
``H' × W'``, so with ``scene_padding = 2`` the circular FFT convolution is an exact linear one.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import ModelFileError, PsfkitError
from psfkit.forward.geometry import CONVENTIONS, padded_shape
from psfkit.io.atomic import atomic_file
from psfkit.weights import WeightBasis, get_basis

KERNEL_FORMAT = "ekdun-kernels"
KERNEL_VERSION = 1


@dataclass(frozen=True)
class KernelModel:
    """An eigen-kernel (or shift-invariant) forward model, as stored in a kernel file.

    Attributes
    ----------
    kernels : numpy.ndarray
        ``(K, C, Hk, Wk)`` float32, origins at ``(Hk//2, Wk//2)``.
    basis : str
        Weight basis name (``"si"`` for a single shift-invariant kernel).
    convention : {"sensor", "source"}
        Where the weights live.
    sensor_shape : (int, int)
        ``(H', W')``.
    channels : tuple of str
        ``("R", "G", "B")`` or ``("L",)``.
    optical_center : (float, float) or None
        ``(v_c, u_c)``; ``None`` is the sensor centre.
    scene_padding : int
        Size of the convolution grid as a multiple of the sensor size (>= 2; 2 by default).
    normalization : str
        Description of the kernels' scale (e.g. ``"base kernel sums to 1 per channel"``).
    provenance : dict
        Where the model came from (input files, fit residuals, ...).
    """

    kernels: np.ndarray
    basis: str = "paper"
    convention: str = "sensor"
    sensor_shape: tuple[int, int] = (0, 0)
    channels: tuple[str, ...] = ("R", "G", "B")
    optical_center: tuple[float, float] | None = None
    scene_padding: int = 2
    normalization: str = "unspecified"
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        kernels = np.asarray(self.kernels)
        object.__setattr__(self, "kernels", kernels.astype(np.float32, copy=False))
        if self.sensor_shape == (0, 0):
            object.__setattr__(self, "sensor_shape", tuple(kernels.shape[-2:]))
        validate_model(self.kernels, self.basis, self.convention, self.sensor_shape,
                       self.channels, self.scene_padding, where="kernel model")

    @property
    def weight_basis(self) -> WeightBasis:
        return get_basis(self.basis)

    @property
    def kernel_names(self) -> tuple[str, ...]:
        return self.weight_basis.kernel_names

    @property
    def padded_shape(self) -> tuple[int, int]:
        """Size of the grid on which the convolutions run (:func:`psfkit.forward.padded_shape`)."""
        return padded_shape(self.sensor_shape, self.scene_padding)

    def weight_maps(self) -> np.ndarray:
        """``(K, H', W')`` float64 weights (of the sensor pixels or of the scene pixels,
        depending on ``convention``; both arrays have the sensor's size)."""
        return self.weight_basis.maps(self.sensor_shape, self.optical_center)

    @classmethod
    def shift_invariant(cls, psf: np.ndarray, **kwargs: Any) -> KernelModel:
        """A one-kernel model from a ``(C, H, W)`` PSF (origin at its centre)."""
        psf = np.asarray(psf)
        if psf.ndim != 3:
            raise ModelFileError(f"a PSF must be (C, H, W), got shape {psf.shape}")
        channels = ("L",) if psf.shape[0] == 1 else ("R", "G", "B")
        kwargs.setdefault("channels", channels)
        return cls(kernels=psf[None], basis="si", **kwargs)


def validate_model(kernels: np.ndarray, basis_name: str, convention: str,
                   sensor_shape: tuple[int, int], channels: tuple[str, ...], scene_padding: int,
                   where: str) -> None:
    """Raise :class:`ModelFileError` naming ``where`` if the pieces of a model disagree."""
    k = kernels
    try:
        basis = get_basis(basis_name)
    except PsfkitError as exc:
        raise ModelFileError(f"{where}: {exc}") from None
    if k.ndim != 4:
        raise ModelFileError(f"{where}: kernels must be (K, C, H, W), got shape {k.shape}")
    if k.shape[0] != basis.n_kernels:
        raise ModelFileError(f"{where}: basis {basis_name!r} needs {basis.n_kernels} kernels "
                             f"{basis.kernel_names}, the file has {k.shape[0]}")
    if k.shape[1] != len(channels) or len(channels) not in (1, 3):
        raise ModelFileError(f"{where}: kernels have {k.shape[1]} channel(s) but channels are "
                             f"{list(channels)}")
    if convention not in CONVENTIONS:
        raise ModelFileError(f"{where}: convention must be 'sensor' or 'source', got "
                             f"{convention!r}")
    if len(sensor_shape) != 2 or min(sensor_shape) < 2:
        raise ModelFileError(f"{where}: sensor_shape {list(sensor_shape)} is not a valid size")
    h, w = sensor_shape
    if not isinstance(scene_padding, int) or scene_padding < 2:
        raise ModelFileError(f"{where}: scene_padding must be an integer >= 2")
    if k.shape[2] > h or k.shape[3] > w:
        raise ModelFileError(f"{where}: kernels {k.shape[2]}x{k.shape[3]} are larger than the "
                             f"sensor {h}x{w}")
    if not np.all(np.isfinite(k)):
        raise ModelFileError(f"{where}: kernels contain NaN/Inf values")


def save_kernels(path: str | os.PathLike, model: KernelModel) -> Path:
    """Write a kernel file atomically (``.npz``)."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ModelFileError(f"{path}: kernel files are .npz")
    meta = {
        "format": KERNEL_FORMAT, "version": KERNEL_VERSION,
        "basis": model.basis, "convention": model.convention,
        "kernel_names": list(model.kernel_names), "channels": list(model.channels),
        "sensor_shape": list(model.sensor_shape),
        "optical_center": None if model.optical_center is None else list(model.optical_center),
        "scene_padding": model.scene_padding, "normalization": model.normalization,
        "kernel_origin": "array centre (H//2, W//2)",
        "provenance": model.provenance,
    }
    with atomic_file(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, kernels=model.kernels, metadata=np.array(json.dumps(meta)))
    return path


def load_kernels(path: str | os.PathLike) -> KernelModel:
    """Read and validate a kernel file; never executes code (no pickles)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such kernel file")
    try:
        with np.load(path, allow_pickle=False) as data:
            if "kernels" not in data.files or "metadata" not in data.files:
                raise ModelFileError(f"{path}: not a kernel file (needs 'kernels' and "
                                     "'metadata' arrays)")
            kernels = np.array(data["kernels"])
            meta = json.loads(str(data["metadata"]))
    except ModelFileError:
        raise
    except (ValueError, OSError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ModelFileError(f"{path}: not a readable kernel file ({reason})") from None
    if not isinstance(meta, dict) or meta.get("format") != KERNEL_FORMAT:
        raise ModelFileError(f"{path}: not an {KERNEL_FORMAT} file")
    if meta.get("version") != KERNEL_VERSION:
        raise ModelFileError(f"{path}: kernel file version {meta.get('version')!r} is not "
                             f"supported (this toolkit reads version {KERNEL_VERSION})")
    try:
        values = dict(
            kernels=kernels.astype(np.float32, copy=False), basis=meta["basis"],
            convention=meta["convention"], sensor_shape=tuple(meta["sensor_shape"]),
            channels=tuple(meta["channels"]),
            optical_center=None if meta.get("optical_center") is None
            else tuple(meta["optical_center"]),
            scene_padding=meta.get("scene_padding", 2),
            normalization=meta.get("normalization", "unspecified"),
            provenance=meta.get("provenance", {}))
    except (KeyError, TypeError) as exc:
        raise ModelFileError(f"{path}: metadata lacks or mangles {exc}") from None
    validate_model(values["kernels"], values["basis"], values["convention"],
                   values["sensor_shape"], values["channels"], values["scene_padding"],
                   where=str(path))
    model = KernelModel(**values)
    if list(meta.get("kernel_names", model.kernel_names)) != list(model.kernel_names):
        raise ModelFileError(f"{path}: kernel_names {meta.get('kernel_names')} do not match "
                             f"basis {model.basis!r} {list(model.kernel_names)}")
    return model
