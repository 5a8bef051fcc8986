"""The kernel file: the hand-off between measuring (psfkit) and learning (ekdun).

One ``.npz`` file (NumPy, no pickles) holds

``kernels``
    float32 ``(K, C, Hk, Wk)``: the model's kernels in the basis' ``kernel_names`` order, C
    channels (RGB or L), origin at the array centre ``(Hk//2, Wk//2)``.
``metadata``
    a JSON string: ``format`` (``"ekdun-kernels"``), ``version``, ``basis``
    (:mod:`psfkit.forward.weights`), ``convention`` (``"sensor"``: weights multiply each
    kernel's image, Eq. 7; ``"source"``: they multiply the scene), ``kernel_names``,
    ``channels``, ``sensor_shape`` ``[H', W']``, ``optical_center`` ``[v_c, u_c]``,
    ``scene_padding`` (the grid is ``scene_padding × sensor_shape``), ``normalization``,
    ``kernel_origin`` (checked on reading), ``read_options`` (how the fitted data was read,
    :class:`psfkit.io.read_options.ReadOptions`; the default for every consumer) and free-form
    ``provenance``.

The forward model is :mod:`psfkit.forward.convolution`'s (``docs/architecture.md``).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import ModelFileError, PsfkitError
from psfkit.forward.geometry import CONVENTIONS
from psfkit.forward.kernel_checks import (
    KERNEL_ORIGIN,
    check_declared_members,
    check_kernels,
    checked_metadata,
    two_finite_numbers,
)
from psfkit.forward.weights import WeightBasis, get_basis
from psfkit.io.atomic import atomic_file
from psfkit.io.json_documents import dumps_finite, load_json_document
from psfkit.io.read_options import ReadOptions
from psfkit.io.validation import (
    MAX_IMAGE_PIXELS,
    MAX_KERNEL_GAIN,
    MAX_SCENE_PADDING,
    MIN_KERNEL_GAIN,
)

KERNEL_FORMAT = "ekdun-kernels"
KERNEL_VERSION = 1
_DEFAULT_WHERE = "kernel model"   # how a model without a file names itself in errors


@dataclass(frozen=True)
class KernelModel:
    """An eigen-kernel (or shift-invariant) forward model, as stored in a kernel file.

    Attributes
    ----------
    kernels : numpy.ndarray
        ``(K, C, Hk, Wk)`` float32, origins at ``(Hk//2, Wk//2)``.
    basis : str
        Weight basis name (``"si"``: one shift-invariant kernel).
    convention : {"sensor", "source"}
    sensor_shape : (int, int)
        ``(H', W')``.
    channels : tuple of str
        ``("R", "G", "B")`` or ``("L",)``.
    optical_center : (float, float) or None
        ``(v_c, u_c)``; ``None``: the sensor centre.
    scene_padding : int
        Convolution grid as a multiple of the sensor size (>= 2).
    normalization : str
        How the kernels are scaled.
    provenance : dict
        Where the model came from.
    read_options : ReadOptions or None
        How the fitted data was read (``None``: not recorded; :meth:`data_read_options`).
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
    read_options: ReadOptions | None = None

    def __post_init__(self) -> None:
        kernels = np.asarray(self.kernels)
        if not np.issubdtype(kernels.dtype, np.number) or np.issubdtype(kernels.dtype,
                                                                         np.complexfloating):
            raise ModelFileError(f"{_DEFAULT_WHERE}: kernels must be real numbers, got dtype "
                                 f"{kernels.dtype}")
        object.__setattr__(self, "kernels", kernels.astype(np.float32, copy=False))
        try:
            shape = tuple(self.sensor_shape)
        except TypeError:
            raise ModelFileError(f"{_DEFAULT_WHERE}: sensor_shape {self.sensor_shape!r} is not "
                                 "a valid size") from None
        if shape == (0, 0):
            shape = tuple(kernels.shape[-2:])
        # NumPy integers become ints so that the metadata is JSON; anything else is refused.
        object.__setattr__(self, "sensor_shape", tuple(
            int(s) if isinstance(s, np.integer) else s for s in shape))
        self.validate(_DEFAULT_WHERE)

    def validate(self, where: str = _DEFAULT_WHERE) -> None:
        """Check that the pieces of the model agree: the one check of the kernel-file contract.

        Run on construction, saving, loading and by ekdun before training.

        Parameters
        ----------
        where : str
            What the model is (a path, ``"seed kernels"``); starts the error message.

        Raises
        ------
        ModelFileError
            Unknown basis or wrong kernel count, bad kernel array (:func:`check_kernels`), channels,
            convention, ``sensor_shape``, ``scene_padding`` or ``optical_center``; kernels all zero
            or with a gain outside ``MIN_KERNEL_GAIN..MAX_KERNEL_GAIN``.
        """
        try:
            basis = get_basis(self.basis)
        except PsfkitError as exc:
            raise ModelFileError(f"{where}: {exc}") from None
        shape = self.sensor_shape
        if (len(shape) != 2 or not all(isinstance(s, (int, np.integer)) for s in shape)
                or min(shape) < 2):
            raise ModelFileError(f"{where}: sensor_shape {list(shape)} is not a valid size")
        check_kernels(self.kernels, shape, where)
        k = self.kernels
        if not np.any(k):
            # a model that predicts a black image for every scene: a fit that went wrong (an
            # empty support mask), never a camera; refused when written and when read
            raise ModelFileError(f"{where}: every kernel is zero (the model predicts a black "
                                 "image for every scene)")
        if k.shape[0] != basis.n_kernels:
            raise ModelFileError(f"{where}: basis {self.basis!r} needs {basis.n_kernels} "
                                 f"kernels {basis.kernel_names}, the file has {k.shape[0]}")
        if k.shape[1] != len(self.channels) or len(self.channels) not in (1, 3):
            raise ModelFileError(f"{where}: kernels have {k.shape[1]} channel(s) but channels "
                                 f"are {list(self.channels)}")
        gain = np.abs(k).sum(axis=(2, 3), dtype=np.float64)   # (K, C)
        if gain.max() > MAX_KERNEL_GAIN:
            i, c = np.unravel_index(int(np.argmax(gain)), gain.shape)
            raise ModelFileError(f"{where}: kernel {basis.kernel_names[i]!r} ({self.channels[c]}) "
                                 f"sums to {gain[i, c]:.3g} in absolute value, more than the "
                                 f"{MAX_KERNEL_GAIN:g} a forward model can apply in float32 "
                                 "without overflowing (a PSF normalised to unit peak or sum is "
                                 "far below)")
        if gain.max() < MIN_KERNEL_GAIN:
            raise ModelFileError(f"{where}: the largest kernel sums to {gain.max():.3g} in "
                                 f"absolute value, less than {MIN_KERNEL_GAIN:g}: the model "
                                 "predicts an almost black image and cannot be inverted in "
                                 "float32 (a PSF normalised to unit peak or sum is far above)")
        if self.convention not in CONVENTIONS:
            raise ModelFileError(f"{where}: convention must be 'sensor' or 'source', got "
                                 f"{self.convention!r}")
        if (isinstance(self.scene_padding, bool) or not isinstance(self.scene_padding, int)
                or not 2 <= self.scene_padding <= MAX_SCENE_PADDING):
            raise ModelFileError(f"{where}: scene_padding must be an integer in 2..."
                                 f"{MAX_SCENE_PADDING}, got {self.scene_padding!r}")
        h, w = int(shape[0]), int(shape[1])
        if self.scene_padding**2 * h * w > 4 * MAX_IMAGE_PIXELS:   # before torch allocates it
            raise ModelFileError(f"{where}: the convolution grid {self.scene_padding}x{h} x "
                                 f"{self.scene_padding}x{w} exceeds the limit of "
                                 f"{4 * MAX_IMAGE_PIXELS} pixels")
        centre = self.optical_center
        if centre is not None and not two_finite_numbers(centre):
            raise ModelFileError(f"{where}: optical_center must be None or two finite numbers "
                                 f"(v_c, u_c), got {centre!r}")

    def to_metadata(self) -> dict[str, Any]:
        """The model without its kernels as JSON-able values (a kernel file's or checkpoint's
        ``metadata``); inverse of :meth:`from_metadata`."""
        return {
            "format": KERNEL_FORMAT, "version": KERNEL_VERSION,
            "basis": self.basis, "convention": self.convention,
            "kernel_names": list(self.kernel_names), "channels": list(self.channels),
            "sensor_shape": [int(s) for s in self.sensor_shape],
            "optical_center": None if self.optical_center is None
            else [float(c) for c in self.optical_center],
            "scene_padding": self.scene_padding, "normalization": self.normalization,
            "kernel_origin": KERNEL_ORIGIN,
            "provenance": self.provenance,
            **({} if self.read_options is None
               else {"read_options": self.read_options.to_json()}),
        }

    def data_read_options(self) -> ReadOptions:
        """How inputs for this model are read by default: :attr:`read_options`, or for older files
        the binning in ``provenance['downsample']``."""
        if self.read_options is not None:
            return self.read_options
        factor = self.provenance.get("downsample")
        ok = isinstance(factor, int) and not isinstance(factor, bool) and 1 <= factor <= 64
        return ReadOptions(downsample=factor if ok else None)

    @classmethod
    def from_metadata(cls, kernels: np.ndarray, meta: dict[str, Any],
                      where: str = _DEFAULT_WHERE) -> KernelModel:
        """The model of ``kernels`` ``(K, C, Hk, Wk)`` and ``meta`` (:meth:`to_metadata`'s).

        ``format`` and ``version`` may be absent (checked by :func:`load_kernels`), as may
        ``scene_padding``, ``normalization``, ``optical_center``, ``kernel_names`` and
        ``provenance``.

        Raises
        ------
        ModelFileError
            A missing or mangled field, or a model failing :meth:`validate` (message starts with
            ``where``).
        """
        if not isinstance(meta, dict):
            raise ModelFileError(f"{where}: metadata is not a JSON object")
        try:
            values = checked_metadata(meta, f"{where}: metadata")
        except KeyError as exc:
            raise ModelFileError(f"{where}: metadata lacks {exc}") from None
        except PsfkitError as exc:
            raise ModelFileError(str(exc)) from None
        try:
            model = cls(kernels=kernels, **values)
        except ModelFileError as exc:
            # Re-issued with ``where`` in front of the problem (construction says "kernel model").
            reason = str(exc).removeprefix(f"{_DEFAULT_WHERE}: ")
            raise ModelFileError(f"{where}: {reason}") from None
        except (TypeError, ValueError) as exc:
            raise ModelFileError(f"{where}: metadata mangles a field ({exc})") from None
        names = meta.get("kernel_names", list(model.kernel_names))
        if list(names) != list(model.kernel_names):
            raise ModelFileError(f"{where}: kernel_names {names} do not match basis "
                                 f"{model.basis!r} {list(model.kernel_names)}")
        return model

    @property
    def weight_basis(self) -> WeightBasis:
        return get_basis(self.basis)

    @property
    def kernel_names(self) -> tuple[str, ...]:
        return self.weight_basis.kernel_names

    def weight_maps(self, extent: tuple[int, int] | None = None) -> np.ndarray:
        """``(K, H', W')`` float64 weights (of sensor or scene pixels, per ``convention``), or on a
        larger centred grid ``extent`` with the edge weights continued (:meth:`WeightBasis.maps`).
        """
        return self.weight_basis.maps(self.sensor_shape, self.optical_center, extent)

    @classmethod
    def shift_invariant(cls, psf: np.ndarray, **kwargs: Any) -> KernelModel:
        """A one-kernel model from a ``(C, H, W)`` PSF (origin at its centre)."""
        psf = np.asarray(psf)
        if psf.ndim != 3:
            raise ModelFileError(f"a PSF must be (C, H, W), got shape {psf.shape}")
        channels = ("L",) if psf.shape[0] == 1 else ("R", "G", "B")
        kwargs.setdefault("channels", channels)
        return cls(kernels=psf[None], basis="si", **kwargs)


def save_kernels(path: str | os.PathLike, model: KernelModel) -> Path:
    """Write a kernel file atomically (``.npz``)."""
    path = Path(path)
    if path.suffix != ".npz":
        raise ModelFileError(f"{path}: kernel files are .npz")
    model.validate(where=str(path))
    text = dumps_finite(model.to_metadata(), f"{path}: metadata")  # never a bare NaN in a file
    with atomic_file(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, kernels=model.kernels, metadata=np.array(text))
    return path


def load_kernels(path: str | os.PathLike) -> KernelModel:
    """Read and validate a kernel file; never executes code (no pickles)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such kernel file")
    try:
        check_declared_members(path)
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
    return KernelModel.from_metadata(kernels, meta, where=str(path))
