"""The checks of a kernel file's contents: kernel array against the sensor (shared with ekdun's
operators), metadata fields and the archive members' declared sizes, before anything large is
allocated.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import ModelFileError, PsfkitError
from psfkit.io.read_options import ReadOptions
from psfkit.io.validation import (
    MAX_IMAGE_PIXELS,
    MAX_JSON_BYTES,
    bounded_size,
    check_array_shape,
    finite_number,
    npy_header,
)

KERNEL_ORIGIN = "array centre (H//2, W//2)"   # the one convention (docs/architecture.md)


def checked_metadata(meta: dict[str, Any], where: str) -> dict[str, Any]:
    """The model fields of kernel metadata, each checked for type and range, before anything is
    allocated; ``KeyError`` for a missing field."""
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
    center = _optical_center(meta.get("optical_center"), sensor, where)
    provenance = meta.get("provenance", {})
    if not isinstance(provenance, dict):
        raise ModelFileError(f"{where}: 'provenance' must be an object, got {provenance!r}")
    origin = meta.get("kernel_origin", KERNEL_ORIGIN)
    if origin != KERNEL_ORIGIN:
        raise ModelFileError(f"{where}: 'kernel_origin' is {origin!r}; this toolkit stores "
                             f"kernels with their origin at the {KERNEL_ORIGIN}")
    read_options = _read_options(meta, where)
    padding = meta.get("scene_padding", 2)
    if isinstance(padding, bool) or not isinstance(padding, int):
        raise ModelFileError(f"{where}: 'scene_padding' must be an integer, got {padding!r}")
    return dict(basis=text("basis", meta["basis"]),
                convention=text("convention", meta["convention"]),
                sensor_shape=sensor, channels=tuple(channels), optical_center=center,
                scene_padding=padding,
                normalization=text("normalization", meta.get("normalization", "unspecified")),
                provenance=provenance, read_options=read_options)


def _optical_center(center: Any, sensor: tuple[int, ...], where: str
                    ) -> tuple[float, float] | None:
    """The metadata's ``optical_center`` ``[v, u]`` (finite, within ten sensor sizes)."""
    if center is None:
        return None
    if not isinstance(center, list) or len(center) != 2:
        raise ModelFileError(f"{where}: 'optical_center' must be [v, u], got {center!r}")
    low, high = -10.0 * max(sensor), 10.0 * max(sensor)
    v, u = (finite_number(x, f"{where}: 'optical_center'", low, high) for x in center)
    return v, u


def _read_options(meta: dict[str, Any], where: str) -> ReadOptions | None:
    """The recorded ``read_options``, or ``None`` (older files record only a checked
    ``provenance['downsample']``)."""
    read_options = meta.get("read_options")
    if read_options is not None:
        return ReadOptions.from_json(read_options, where)
    if isinstance(meta.get("provenance"), dict) and "downsample" in meta["provenance"]:
        factor = meta["provenance"]["downsample"]
        if isinstance(factor, bool) or not isinstance(factor, int) or not 1 <= factor <= 64:
            raise ModelFileError(f"{where}: provenance 'downsample' must be an integer in "
                                 f"1..64, got {factor!r}")
    return None


def two_finite_numbers(values: Any) -> bool:
    """Whether ``values`` is a pair of finite numbers (an ``optical_center``)."""
    try:
        return len(values) == 2 and all(np.isfinite(float(v)) for v in values)
    except (TypeError, ValueError):
        return False


def check_kernels(kernels: Any, sensor_shape: tuple[int, int], where: str = "",
                  error: type[PsfkitError] = ModelFileError) -> None:
    """Check a kernel array ``(K, C, Hk, Wk)`` against the sensor ``(H', W')``.

    Parameters
    ----------
    kernels : numpy.ndarray or torch.Tensor
        A tensor is checked with its own methods (on its device, without importing torch).
    sensor_shape : (int, int)
        ``(H', W')``; a kernel may not be larger.
    where : str
        Starts the message (``"{where}: ..."``) when not empty.
    error : PsfkitError subclass
        The class raised (ekdun raises its ``KernelShapeError``).

    Raises
    ------
    error
        Not 4-D, no kernel or channel, not floating point, larger than the sensor, NaN/Inf.
    """
    prefix = f"{where}: " if where else ""
    shape = tuple(int(s) for s in kernels.shape)
    if len(shape) != 4:
        raise error(f"{prefix}kernels must be (K, C, H, W), got shape {shape}")
    if shape[0] < 1 or shape[1] < 1:
        raise error(f"{prefix}kernels must have at least one kernel and channel, got shape "
                    f"{shape}")
    if hasattr(kernels, "is_floating_point"):
        floating = bool(kernels.is_floating_point())
    else:
        floating = bool(np.issubdtype(np.asarray(kernels).dtype, np.floating))
    if not floating:
        raise error(f"{prefix}kernels must be float32 or float64, got {kernels.dtype}")
    h, w = int(sensor_shape[0]), int(sensor_shape[1])
    if shape[2] > h or shape[3] > w:
        raise error(f"{prefix}kernels {shape[2]}x{shape[3]} are larger than the sensor {h}x{w}")
    finite = (kernels.isfinite().all() if hasattr(kernels, "isfinite")
              else np.isfinite(kernels).all())
    if not bool(finite):
        raise error(f"{prefix}kernels contain NaN/Inf values")


def check_declared_members(path: Path) -> None:
    """Refuse a kernel file whose members declare absurd sizes (``.npy`` headers and zip sizes), so
    compressed zeros cannot make :func:`numpy.load` inflate gigabytes."""
    # bytes: kernels of MAX_IMAGE_PIXELS float64 values, metadata of MAX_JSON_BYTES characters
    limits = {"kernels": 8 * MAX_IMAGE_PIXELS, "metadata": 4 * MAX_JSON_BYTES}
    with zipfile.ZipFile(path) as archive:
        for name, max_bytes in limits.items():
            try:
                info = archive.getinfo(f"{name}.npy")
            except KeyError:
                continue            # np.load reports the missing member
            what = f"{path}: member '{name}'"
            with archive.open(info) as member:
                shape, _, dtype = npy_header(member, what)
                header_bytes = member.tell()
            if dtype.hasobject:    # pickled objects: never loaded (np.load would refuse too)
                raise ModelFileError(f"{path}: not a readable kernel file (member '{name}' "
                                     "holds Python objects)")
            elements = check_array_shape(shape, dtype, what, MAX_IMAGE_PIXELS)
            declared = int(np.prod(elements, dtype=np.int64)) * dtype.itemsize
            if declared > max_bytes:
                raise ModelFileError(f"{what}: declares {declared} bytes, more than the "
                                     f"{max_bytes} a kernel file may hold")
            if info.file_size > header_bytes + declared:
                raise ModelFileError(f"{what}: the archive declares {info.file_size} bytes for "
                                     f"an array of {declared}")
