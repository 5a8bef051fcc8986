"""Checkpoints of trained networks: tensors + JSON metadata, written atomically, read without
pickles.

A checkpoint is a ``dict`` saved with :func:`torch.save` whose leaves are tensors, strings and
numbers only, so it loads with ``torch.load(weights_only=True)`` (never runs code; anything
else is refused with :class:`CheckpointError`). Keys: ``format``, ``version``; ``metadata``
(JSON: model, preset, overrides, sensor shape, kernel-file metadata, epoch, options, history);
``model`` (the ``state_dict``); ``initial_kernels`` ``(K, C, Hk, Wk)`` (the seed kernel model);
``optimizer``, ``scheduler``, ``scaler`` (training only); ``rng`` (:mod:`ekdun.training.rng`).
"""

from __future__ import annotations

import json
import os
import pickle
import re
import zipfile
from pathlib import Path
from typing import Any

import torch

from ekdun.errors import CheckpointError
from ekdun.flag_ranges import MAX_UNROLLED_ITERATIONS
from psfkit.errors import PsfkitError
from psfkit.io.atomic import atomic_file
from psfkit.io.json_documents import load_json_document
from psfkit.io.validation import bounded_size, exact_int

__all__ = ["FORMAT", "VERSION", "CheckpointError", "checkpoint_sensor", "load_checkpoint",
           "save_checkpoint"]  # CheckpointError: defined in ekdun.errors

FORMAT = "ekdun-checkpoint"
VERSION = 1


def save_checkpoint(path: str | os.PathLike, state: dict[str, Any]) -> Path:
    """Write ``state`` (plus ``format``/``version``) atomically with :func:`torch.save`."""
    path = Path(path)
    doc = {"format": FORMAT, "version": VERSION, **state}
    if not isinstance(doc.get("metadata"), str):
        doc["metadata"] = json.dumps(doc.get("metadata", {}))
    with atomic_file(path) as tmp:
        torch.save(doc, tmp)
    return path


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu"
                    ) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True``; ``metadata`` decoded from JSON.

    Raises
    ------
    CheckpointError
        Missing file, not a torch file, unsafe content (pickled objects), wrong format.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint")
    try:
        doc = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"(GLOBAL [\w.]+|Unsupported global: [\w. ]+)", str(exc))
        if found:
            raise CheckpointError(f"{path}: refused to load: it contains pickled objects "
                                  f"({found.group(1).strip()}) whose loading would run code; "
                                  "not an ekdun checkpoint") from None
        raise CheckpointError(f"{path}: not a readable checkpoint (corrupt or not a torch "
                              "file)") from None
    except (RuntimeError, EOFError, OSError, ValueError, zipfile.BadZipFile,
            AttributeError, TypeError, KeyError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{path}: not a readable checkpoint ({first[:120]})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not an {FORMAT} file")
    if doc.get("version") != VERSION:
        raise CheckpointError(f"{path}: checkpoint version {doc.get('version')!r} is not "
                              f"supported (this ekdun reads version {VERSION})")
    for key in ("metadata", "model"):
        if key not in doc:
            raise CheckpointError(f"{path}: checkpoint lacks {key!r}")
    if not isinstance(doc["metadata"], str):
        raise CheckpointError(f"{path}: checkpoint metadata is not a JSON string")
    try:   # psfkit's input errors (JSON, sizes) as checkpoint errors
        doc["metadata"] = load_json_document(doc["metadata"], f"{path}: metadata")
        _check_contents(doc, path)
    except CheckpointError:
        raise
    except PsfkitError as exc:
        raise CheckpointError(str(exc)) from None
    return doc


def _check_contents(doc: dict[str, Any], path: Path) -> None:
    """Refuse absurd metadata sizes and non-finite weights (one NaN makes every output NaN)."""
    meta = doc["metadata"]
    if not isinstance(meta, dict):
        raise CheckpointError(f"{path}: checkpoint metadata is not an object")
    overrides = meta.get("overrides", {})
    if not isinstance(overrides, dict):
        raise CheckpointError(f"{path}: metadata 'overrides' must be an object")
    if "iterations" in overrides:
        exact_int(overrides["iterations"], f"{path}: metadata 'iterations'", 1,
                  MAX_UNROLLED_ITERATIONS)
    _check_declared_network(meta, doc["model"], path)
    for key in ("model", "initial_kernels"):
        tensors = doc.get(key)
        items = tensors.items() if isinstance(tensors, dict) else [(key, tensors)]
        for name, tensor in items:
            if isinstance(tensor, torch.Tensor) and tensor.is_floating_point() \
                    and not bool(torch.isfinite(tensor).all()):
                bad = int((~torch.isfinite(tensor)).sum())
                raise CheckpointError(f"{path}: {key} tensor {name!r} contains {bad} "
                                      "NaN/Inf value(s)")


def _declared_widths(value: Any, key: str = "") -> list[tuple[str, Any]]:
    """Every ``widths`` list in the metadata's configuration overrides, with its key."""
    if isinstance(value, dict):
        return [found for k, v in value.items()
                for found in ([(f"{key}{k}", v)] if k == "widths"
                              else _declared_widths(v, f"{key}{k}."))]
    return []


def _check_declared_network(meta: dict[str, Any], state: Any, path: Path) -> None:
    """Check the metadata's network against the stored weights before it is built (building
    allocates what the metadata says): every declared layer must fit in the largest stored
    tensor, and the declared sensor must be that of the stored weight maps."""
    if not isinstance(state, dict):
        raise CheckpointError(f"{path}: checkpoint 'model' is not a dict of tensors")
    sizes = [t.numel() for t in state.values() if isinstance(t, torch.Tensor)]
    largest = max(sizes, default=0)
    for key, widths in _declared_widths(meta.get("overrides", {})):
        what = f"{path}: metadata '{key}'"
        if not isinstance(widths, list) or not 1 <= len(widths) <= 8:
            raise CheckpointError(f"{what} must be a list of 1 to 8 integers")
        values = [exact_int(w, what, 1, 4096) for w in widths]
        # a 3 x 3 convolution between consecutive widths (and within one width)
        layer = max(9 * a * b for a, b in zip(values, values[1:] + values[-1:], strict=True))
        if layer > largest:
            raise CheckpointError(f"{what} {values} declares a layer of {layer} weights, "
                                  f"but the file's largest tensor has {largest}")
    sensor = bounded_size(meta.get("sensor_shape", ()), f"{path}: metadata 'sensor_shape'")
    kernel_meta = meta.get("kernel_metadata")
    if not isinstance(kernel_meta, dict) or \
            list(kernel_meta.get("sensor_shape") or ()) != list(sensor):
        raise CheckpointError(f"{path}: metadata 'sensor_shape' {list(sensor)} is not its "
                              "kernel metadata's")
    maps = state.get("physics.weights")   # EK-DUN's weight maps have the sensor's size
    if isinstance(maps, torch.Tensor) and tuple(maps.shape[-2:]) != tuple(sensor):
        raise CheckpointError(f"{path}: metadata 'sensor_shape' {list(sensor)} differs from "
                              f"the stored weight maps {list(maps.shape[-2:])}")


def checkpoint_sensor(doc: dict[str, Any]) -> tuple[int, int, int]:
    """``(C, H', W')`` of the measurements a checkpoint's network takes (from its metadata,
    checked by :func:`load_checkpoint`), for checking inputs before the network is built."""
    meta = doc["metadata"]
    channels = len(meta.get("kernel_metadata", {}).get("channels") or ()) or 3
    height, width = meta["sensor_shape"]
    return channels, int(height), int(width)
