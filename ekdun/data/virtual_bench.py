"""The virtual-bench dataset: scenes, simulated measurements and the bench's PSF grid.

``make_virtual_bench(root, spec)`` builds (once) ``manifest.json`` (spec, versions, file list,
content hash), ``grid/`` (the bench's PSF grid in psfkit's grid format, for ``psfkit
fit-eigen``) and the pairs folders ``train/`` and ``test/`` (``scene/`` and ``measurement/``
``.npy`` files, ``(H', W', 3)`` float32 RGB). Scenes are dead leaves and crops of
scikit-image's natural images; measurements come from the dense shift-variant model with
Poisson–Gaussian noise, never the eigen-kernel model the networks use. Everything is
deterministic given ``spec.seed``; a folder whose manifest matches is reused, one that
disagrees is rebuilt, any other non-empty folder is refused.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ekdun.data.bench_spec import (
    FULL_PIXEL_UM,
    TEST_IMAGES,
    TRAIN_IMAGES,
    VirtualBenchSpec,
    dense_model_for,
    make_scenes,
    node_psfs,
)
from ekdun.data.dense_model import DenseShiftVariantModel
from ekdun.errors import ConfigurationError, InvalidInputError
from psfkit.io.atomic import atomic_directory, atomic_file
from psfkit.io.images import write_image
from psfkit.io.json_documents import read_json_file
from psfkit.simulate import simulate_grid

__all__ = ["FORMAT", "FULL_PIXEL_UM", "MANIFEST", "TEST_IMAGES", "TRAIN_IMAGES", "VERSION",
           "VirtualBenchSpec", "content_hash", "dataset_is_current", "dense_model_for",
           "make_scenes", "make_virtual_bench", "node_psfs", "read_manifest",
           "resolve_split", "simulate_measurements"]

FORMAT = "ekdun-virtual-bench"
VERSION = 1
MANIFEST = "manifest.json"


def _versions() -> dict[str, str]:
    import numpy
    import skimage

    from ekdun import __version__ as ekdun_version
    return {"format": f"{FORMAT}/{VERSION}", "ekdun": ekdun_version, "numpy": numpy.__version__,
            "torch": torch.__version__.split("+")[0], "scikit-image": skimage.__version__}


def simulate_measurements(model: DenseShiftVariantModel, scenes: np.ndarray,
                          spec: VirtualBenchSpec, split_id: int, batch: int = 8,
                          progress: bool = False) -> np.ndarray:
    """Noisy measurements of ``scenes`` (Poisson–Gaussian, drawn on the CPU from per-image
    seeds)."""
    from tqdm.auto import tqdm

    out = np.empty_like(scenes)
    starts = range(0, len(scenes), batch)
    for start in tqdm(starts, desc=f"measurements ({'test' if split_id else 'train'})",
                      unit="batch", disable=not progress, leave=False):
        clean = model(torch.as_tensor(scenes[start:start + batch])).cpu().numpy()
        for j, y in enumerate(clean):
            i = start + j
            rng = np.random.default_rng([spec.seed, split_id, i, 7])
            electrons = rng.poisson(np.clip(y, 0, None) * spec.photons).astype(np.float64)
            electrons += rng.normal(0.0, spec.read_noise_e, size=y.shape)
            out[i] = (electrons / spec.photons).astype(np.float32)
    return out


def content_hash(root: Path, files: list[str]) -> str:
    """SHA-256 over the relative paths and bytes of ``files`` (sorted)."""
    digest = hashlib.sha256()
    for rel in sorted(files):
        digest.update(rel.encode())
        with open(root / rel, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def _data_files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)).replace(os.sep, "/") for p in root.rglob("*")
                  if p.is_file() and p.name != MANIFEST)


def read_manifest(root: str | os.PathLike) -> dict[str, Any] | None:
    """The manifest of a virtual-bench folder, or ``None`` when there is none."""
    path = Path(root) / MANIFEST
    if not path.is_file():
        return None
    try:
        doc = read_json_file(path)
    except InvalidInputError:
        return None
    return doc if isinstance(doc, dict) and doc.get("format") == FORMAT else None


def resolve_split(data: str | os.PathLike, split: str) -> Path:
    """The pairs folder of ``data``: its ``split`` folder for a virtual-bench dataset, else
    ``data`` itself (:class:`InvalidInputError` unless it is a folder)."""
    root = Path(data)
    if not root.is_dir():
        raise InvalidInputError(f"{root}: no such dataset folder")
    if read_manifest(root) is not None:
        return root / split
    return root


def dataset_is_current(root: str | os.PathLike, spec: VirtualBenchSpec,
                       verify_hash: bool = True) -> bool:
    """Whether ``root`` holds exactly the dataset ``spec`` describes."""
    root = Path(root)
    doc = read_manifest(root)
    if doc is None or doc.get("versions") != _versions():
        return False
    try:
        # through the spec class: a manifest written before a field existed holds its default
        if VirtualBenchSpec.from_dict(doc.get("spec") or {}) != spec:
            return False
    except (TypeError, ConfigurationError):
        return False
    files = _data_files(root)
    if files != doc.get("files"):
        return False
    return not verify_hash or content_hash(root, files) == doc.get("content_hash")


def make_virtual_bench(root: str | os.PathLike, spec: VirtualBenchSpec | None = None,
                       progress: bool = True, verify_hash: bool = True,
                       device: str | torch.device = "cpu", workers: int = 1) -> Path:
    """Build the dataset at ``root`` unless an identical one is already there.

    Parameters
    ----------
    root : path-like
        Dataset folder (created atomically).
    spec : VirtualBenchSpec
        Contents (default: the ``tiny`` dataset).
    progress : bool
    verify_hash : bool
        Re-hash the files of an existing dataset before reusing it.
    device : str or torch.device
        Where the noise-free measurements are computed (float64 on any device).
    workers : int
        Processes drawing the scenes (:func:`make_scenes`).

    Raises
    ------
    InvalidInputError
        ``root`` exists, is not empty and is not a virtual-bench dataset.
    """
    spec = spec or VirtualBenchSpec()
    root = Path(root)
    if dataset_is_current(root, spec, verify_hash):
        return root
    if root.exists() and root.is_dir() and any(root.iterdir()) and read_manifest(root) is None:
        raise InvalidInputError(f"{root}: exists and is not a virtual-bench dataset (no "
                                f"{MANIFEST} of format {FORMAT}); choose another folder")
    with atomic_directory(root, overwrite=True) as tmp:
        simulate_grid(tmp / "grid", spec.bench_config(), grid_shape=spec.grid_shape,
                      suffix=".npy", progress=progress, frames=spec.grid_frames)
        model = dense_model_for(spec).to(device)
        for split_id, split in enumerate(("train", "test")):
            scenes = make_scenes(spec, split, workers=workers, progress=progress)
            measurements = simulate_measurements(model, scenes, spec, split_id,
                                                 progress=progress)
            for sub, arrays in (("scene", scenes), ("measurement", measurements)):
                folder = tmp / split / sub
                folder.mkdir(parents=True)
                for i, image in enumerate(arrays):
                    # the one image writer: refuses NaN/Inf (e.g. --photons 1e-300)
                    write_image(folder / f"{split}{i:04d}.npy", image.astype(np.float32))
        files = _data_files(tmp)
        manifest = {
            "format": FORMAT, "version": VERSION, "spec": spec.to_dict(),
            "versions": _versions(), "bench": spec.bench_config().to_dict(),
            "forward_model": f"dense bilinear interpolation of {spec.grid_shape[0]}x"
                             f"{spec.grid_shape[1]} noise-free bench PSFs ({spec.convention} "
                             "weights) + Poisson-Gaussian noise",
            "files": files, "content_hash": content_hash(tmp, files),
        }
        with atomic_file(tmp / MANIFEST) as out:
            out.write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return root
