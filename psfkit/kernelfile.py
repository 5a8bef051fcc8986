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

import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import ModelFileError, PsfkitError
from psfkit.io.atomic import atomic_file
from psfkit.validation import (
    MAX_IMAGE_PIXELS,
    MAX_SCENE_PADDING,
    bounded_size,
    dumps_finite,
    exact_int,
    finite_number,
    load_json_document,
)
from psfkit.weights import WeightBasis, get_basis

KERNEL_FORMAT = "ekdun-kernels"
KERNEL_VERSION = 1
CONVENTIONS = ("sensor", "source")


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
        """Size of the grid on which the convolutions run."""
        return (self.scene_padding * self.sensor_shape[0],
                self.scene_padding * self.sensor_shape[1])

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
    if isinstance(scene_padding, bool) or not isinstance(scene_padding, int) \
            or not 2 <= scene_padding <= MAX_SCENE_PADDING:
        raise ModelFileError(f"{where}: scene_padding must be an integer in 2..."
                             f"{MAX_SCENE_PADDING}, got {scene_padding!r}")
    if scene_padding**2 * h * w > 4 * MAX_IMAGE_PIXELS:
        raise ModelFileError(f"{where}: the convolution grid {scene_padding}x{h} x "
                             f"{scene_padding}x{w} exceeds the limit of {4 * MAX_IMAGE_PIXELS} "
                             "pixels")
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
    text = dumps_finite(meta, f"{path}: metadata")   # never a bare NaN in a kernel file
    with atomic_file(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, kernels=model.kernels, metadata=np.array(text))
    return path


def _checked_metadata(meta: dict[str, Any], where: str) -> dict[str, Any]:
    """The model fields of a kernel file's metadata, each checked for type and range
    (``where: field ...`` in messages); raises ``KeyError`` for a missing required field."""
    def text(key: str, value: Any) -> str:
        if not isinstance(value, str):
            raise ModelFileError(f"{where}: '{key}' must be a string, got {value!r}")
        return value

    channels = meta["channels"]
    if not isinstance(channels, list) or not all(isinstance(c, str) for c in channels):
        raise ModelFileError(f"{where}: 'channels' must be a list of names, got {channels!r}")
    sensor = tuple(bounded_size(meta["sensor_shape"], f"{where}: 'sensor_shape'"))
    if len(sensor) != 2:
        raise ModelFileError(f"{where}: 'sensor_shape' must be [H, W], got {list(sensor)}")
    center = meta.get("optical_center")
    if center is not None:
        if not isinstance(center, list) or len(center) != 2:
            raise ModelFileError(f"{where}: 'optical_center' must be [v, u], got {center!r}")
        center = tuple(finite_number(v, f"{where}: 'optical_center'", -10.0 * max(sensor),
                                     10.0 * max(sensor)) for v in center)
    provenance = meta.get("provenance", {})
    if not isinstance(provenance, dict):
        raise ModelFileError(f"{where}: 'provenance' must be an object, got {provenance!r}")
    return dict(basis=text("basis", meta["basis"]),
                convention=text("convention", meta["convention"]),
                sensor_shape=sensor, channels=tuple(channels), optical_center=center,
                scene_padding=exact_int(meta.get("scene_padding", 2),
                                        f"{where}: 'scene_padding'", 2, MAX_SCENE_PADDING),
                normalization=text("normalization", meta.get("normalization", "unspecified")),
                provenance=provenance)


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
            text = str(data["metadata"])
    except ModelFileError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ModelFileError(f"{path}: not a readable kernel file ({reason})") from None
    try:
        meta = load_json_document(text, f"{path}: metadata")
    except PsfkitError as exc:
        raise ModelFileError(str(exc)) from None
    if not isinstance(meta, dict) or meta.get("format") != KERNEL_FORMAT:
        raise ModelFileError(f"{path}: not an {KERNEL_FORMAT} file")
    if isinstance(meta.get("version"), bool) or meta.get("version") != KERNEL_VERSION:
        raise ModelFileError(f"{path}: kernel file version {meta.get('version')!r} is not "
                             f"supported (this toolkit reads version {KERNEL_VERSION})")
    try:
        values = _checked_metadata(meta, f"{path}: metadata")
    except KeyError as exc:
        raise ModelFileError(f"{path}: metadata lacks {exc}") from None
    except PsfkitError as exc:
        raise ModelFileError(str(exc)) from None
    if kernels.dtype.kind not in "biuf":
        raise ModelFileError(f"{path}: kernels are {kernels.dtype} data, expected numbers")
    values["kernels"] = kernels.astype(np.float32, copy=False)
    validate_model(values["kernels"], values["basis"], values["convention"],
                   values["sensor_shape"], values["channels"], values["scene_padding"],
                   where=str(path))
    model = KernelModel(**values)
    if list(meta.get("kernel_names", model.kernel_names)) != list(model.kernel_names):
        raise ModelFileError(f"{path}: kernel_names {meta.get('kernel_names')} do not match "
                             f"basis {model.basis!r} {list(model.kernel_names)}")
    return model
