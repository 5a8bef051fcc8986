"""Folders of (scene, measurement) image pairs: two sub-folders (:data:`SCENE_DIRS`,
:data:`MEASUREMENT_DIRS`; the DiffuserCam Mirflickr layout ``lensed/`` + ``diffuser/`` is read as
BGR) whose files pair up by stem, and an optional ``pairs.json`` (``scene_dir``,
``measurement_dir``, ``channel_order``, ``flip`` of the scene, ``white_level``). Images are
float32 in the toolkit's units (:func:`psfkit.io.images.unit_range`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psfkit.errors import InvalidInputError
from psfkit.io.images import IMAGE_SUFFIXES, read_image, unit_range
from psfkit.io.json_documents import read_json_file
from psfkit.io.read_options import FLIPS, ReadOptions
from psfkit.io.validation import MAX_WHITE_LEVEL, finite_number

SCENE_DIRS = ("scene", "scenes", "gt", "ground_truth", "lensed")
MEASUREMENT_DIRS = ("measurement", "measurements", "meas", "raw", "diffuser")
MANIFEST = "pairs.json"
_MANIFEST_KEYS = ("scene_dir", "measurement_dir", "channel_order", "flip", "white_level")


@dataclass(frozen=True)
class PairSet:
    """A validated pairs folder; images are read on demand as ``(C, H, W)`` float32 (RGB,
    integer files scaled to ``[0, 1]`` by ``white_level``)."""

    root: Path
    scene_dir: str
    measurement_dir: str
    names: tuple[str, ...]
    scene_files: tuple[str, ...]
    measurement_files: tuple[str, ...]
    channel_order: str
    flip: str
    shape: tuple[int, int, int]
    dtypes: tuple[str, str] = ("", "")  # pixel types of the scenes and of the measurements
    white_level: float | None = None    # full scale of integer files (None: dtype maximum)

    def __len__(self) -> int:
        return len(self.names)

    def load(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """``(scene, measurement)`` of pair ``index``, ``(C, H, W)`` float32 each; NaN/Inf or
        sizes that differ raise :class:`InvalidInputError`."""
        scene_path = self.root / self.scene_dir / self.scene_files[index]
        measurement_path = self.root / self.measurement_dir / self.measurement_files[index]
        raw_scene = read_image(scene_path, self.channel_order)
        raw_measurement = read_image(measurement_path, self.channel_order)
        for path, raw, dtype in ((scene_path, raw_scene, self.dtypes[0]),
                                 (measurement_path, raw_measurement, self.dtypes[1])):
            # one pixel type per folder: a uint16 file among float ones has another scale
            if dtype and str(raw.dtype) != dtype:
                raise InvalidInputError(f"{path}: pixel type {raw.dtype} differs from the "
                                        f"other files' ({dtype}, as {self.names[0]}); convert "
                                        "them to one type")
        scene = unit_range(raw_scene, str(scene_path), self.white_level)
        measurement = unit_range(raw_measurement, str(measurement_path), self.white_level)
        if scene.shape != measurement.shape:
            raise InvalidInputError(
                f"{scene_path}: scene {scene.shape[1]}×{scene.shape[2]}×{scene.shape[0]} "
                f"differs from its measurement {measurement.shape[1]}×{measurement.shape[2]}×"
                f"{measurement.shape[0]}; the forward model needs scenes at the sensor's size "
                "(resample them first)")
        if any(self.shape) and scene.shape != self.shape:
            raise InvalidInputError(f"{scene_path}: size {scene.shape} differs from "
                                    f"{self.names[0]} ({self.shape})")
        if self.flip in ("ud", "both"):
            scene = scene[:, ::-1]
        if self.flip in ("lr", "both"):
            scene = scene[:, :, ::-1]
        return np.ascontiguousarray(scene), measurement

    def read_options(self, downsample: int = 1) -> ReadOptions:
        """How this folder's files are read (recorded in kernel files and checkpoints)."""
        return ReadOptions(channel_order=self.channel_order, flip=self.flip,
                           downsample=int(downsample), white_level=self.white_level)

    def select(self, holdout: Iterable[str] = (), only: Iterable[str] = ()
               ) -> tuple[int, ...]:
        """Indices of the pairs left after holding ``holdout`` out and, if ``only`` is given,
        keeping only those names (both as :func:`parse_names` reads them); an unknown name or
        no pair left raises :class:`InvalidInputError`."""
        held, selected = parse_names(holdout), parse_names(only)
        for names, what in ((held, "to hold out"), (selected, "to evaluate")):
            unknown = [n for n in names if n not in self.names]
            if unknown:
                raise InvalidInputError(f"{self.root}: no pair named {', '.join(unknown)} "
                                        f"{what} (pairs: {', '.join(self.names[:8])}"
                                        + (", ..." if len(self) > 8 else "") + ")")
        indices = tuple(i for i, n in enumerate(self.names)
                        if n not in held and (not selected or n in selected))
        if not indices:
            raise InvalidInputError(f"{self.root}: every pair is held out; nothing left to "
                                    "fit or train on")
        return indices

    def subset(self, indices: Iterable[int]) -> PairSet:
        """The same folder restricted to the pairs ``indices`` (e.g. from :meth:`select`)."""
        keep = tuple(indices)
        return dataclasses.replace(
            self, names=tuple(self.names[i] for i in keep),
            scene_files=tuple(self.scene_files[i] for i in keep),
            measurement_files=tuple(self.measurement_files[i] for i in keep))

    def load_all(self) -> tuple[np.ndarray, np.ndarray]:
        """All pairs as two ``(N, C, H, W)`` float32 arrays."""
        pairs = [self.load(i) for i in range(len(self))]
        return np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs])


def parse_names(values: Iterable[str] | None) -> tuple[str, ...]:
    """Pair names from repeated and/or comma-separated options (``--holdout a,b --holdout c``);
    a file name's suffix is dropped (``im65.npy`` → ``im65``)."""
    names: list[str] = []
    for value in values or ():
        for part in str(value).split(","):
            part = part.strip()
            if part:
                names.append(os.path.splitext(os.path.basename(part))[0])
    return tuple(dict.fromkeys(names))


def _images(folder: Path) -> dict[str, str]:
    files = {}
    for f in sorted(folder.iterdir()):
        if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES:
            if f.stem in files:
                raise InvalidInputError(f"{folder}: two images named {f.stem!r} "
                                        f"({files[f.stem]}, {f.name})")
            files[f.stem] = f.name
    return files


def _pick(root: Path, choices: tuple[str, ...], what: str) -> str:
    found = [name for name in choices if (root / name).is_dir()]
    if not found:
        raise InvalidInputError(f"{root}: no {what} folder (expected one of "
                                f"{', '.join(choices)}, or name it in {MANIFEST})")
    if len(found) > 1:
        raise InvalidInputError(f"{root}: several {what} folders ({', '.join(found)}); name the "
                                f"right one in {MANIFEST}")
    return found[0]


def _read_manifest(path: Path) -> dict:
    """``pairs.json``: strict JSON, known keys, each a string (names the bad field)."""
    manifest = read_json_file(path)
    if not isinstance(manifest, dict):
        raise InvalidInputError(f"{path}: must be a JSON object")
    unknown = sorted(k for k in manifest if k not in _MANIFEST_KEYS)
    if unknown:
        raise InvalidInputError(f"{path}: unknown key(s) {', '.join(unknown)} (allowed: "
                                f"{', '.join(_MANIFEST_KEYS)})")
    for key, value in manifest.items():
        if key == "white_level":
            # at most what an integer file can store: a larger one would scale images to 0
            level = finite_number(value, f"{path}: 'white_level'", maximum=MAX_WHITE_LEVEL)
            if level <= 0:
                raise InvalidInputError(f"{path}: 'white_level' must be positive, got {value!r}")
            manifest[key] = level
            continue
        if not isinstance(value, str) or not value:
            raise InvalidInputError(f"{path}: '{key}' must be a non-empty string, got {value!r}")
        if key.endswith("_dir"):
            # resolved ("..", symbolic links): the folder must lie inside the pairs folder
            root, inside = path.parent.resolve(), (path.parent / value).resolve()
            if Path(value).name != value or inside == root or not inside.is_relative_to(root):
                raise InvalidInputError(f"{path}: '{key}' must name a sub-folder inside "
                                        f"{path.parent}, got {value!r}")
    return manifest


def read_pairs(root: str | os.PathLike, channel_order: str | None = None,
               check_pixels: bool = True, recorded: ReadOptions | None = None) -> PairSet:
    """Read and validate a pairs folder.

    Parameters
    ----------
    root : path-like
        The folder.
    channel_order : {"RGB", "BGR"}, optional
        Overrides ``pairs.json`` and the layout's default.
    recorded : ReadOptions, optional
        Read options recorded with the model (kernel file, checkpoint): used where neither
        ``channel_order``, ``pairs.json`` nor the layout declares them (else RGB, no flip).
    check_pixels : bool
        Read every pair now (otherwise only the first; :meth:`PairSet.load` checks the rest).

    Raises
    ------
    InvalidInputError
        Missing or ambiguous sub-folders, no or unpaired files, mismatched sizes, NaN/Inf.
    """
    root = Path(root)
    if not root.is_dir():
        raise InvalidInputError(f"{root}: no such pairs folder")
    manifest: dict = {}
    if (root / MANIFEST).is_file():
        manifest = _read_manifest(root / MANIFEST)
    scene_dir = manifest.get("scene_dir") or _pick(root, SCENE_DIRS, "scene")
    measurement_dir = manifest.get("measurement_dir") or _pick(root, MEASUREMENT_DIRS,
                                                               "measurement")
    for name in (scene_dir, measurement_dir):
        if not (root / name).is_dir():
            raise InvalidInputError(f"{root / name}: no such folder")
    dlmd = scene_dir == "lensed" and measurement_dir == "diffuser"
    recorded = recorded or ReadOptions()
    order = (channel_order or manifest.get("channel_order") or ("BGR" if dlmd else None)
             or recorded.channel_order or "RGB")
    if order not in ("RGB", "BGR"):
        raise InvalidInputError(f"{root}: channel_order must be RGB or BGR, got {order!r}")
    flip = manifest.get("flip", recorded.flip)
    if flip not in FLIPS:
        raise InvalidInputError(f"{root / MANIFEST}: flip must be one of {FLIPS}")

    scenes, measurements = _images(root / scene_dir), _images(root / measurement_dir)
    if not scenes and not measurements:
        raise InvalidInputError(f"{root}: empty pairs folder (no images in {scene_dir}/ or "
                                f"{measurement_dir}/)")
    unpaired = sorted(set(scenes) ^ set(measurements))
    if unpaired:
        where = [f"{scene_dir}/{scenes[n]}" if n in scenes else
                 f"{measurement_dir}/{measurements[n]}" for n in unpaired[:4]]
        raise InvalidInputError(f"{root}: unpaired file(s) {', '.join(where)}"
                                + (f" and {len(unpaired) - 4} more" if len(unpaired) > 4 else ""))
    names = tuple(sorted(scenes))
    pairs = PairSet(root=root, scene_dir=scene_dir, measurement_dir=measurement_dir,
                    names=names, scene_files=tuple(scenes[n] for n in names),
                    measurement_files=tuple(measurements[n] for n in names),
                    channel_order=order, flip=flip, shape=(0, 0, 0),
                    white_level=manifest.get("white_level", recorded.white_level))
    # every image is validated as it is loaded: the first fixes the set's size and pixel type
    dtypes = tuple(str(read_image(root / folder / files[0], order).dtype) for folder, files in
                   ((scene_dir, pairs.scene_files), (measurement_dir, pairs.measurement_files)))
    pairs = dataclasses.replace(pairs, dtypes=dtypes)
    shape = pairs.load(0)[0].shape
    pairs = dataclasses.replace(pairs, shape=shape)
    for i in range(1, len(names) if check_pixels else 1):
        pairs.load(i)
    return pairs
