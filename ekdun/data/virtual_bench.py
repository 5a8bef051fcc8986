"""The virtual-bench dataset: scenes, simulated measurements and the bench's PSF grid.

``make_virtual_bench(root, spec)`` builds (once) a folder ::

    root/
      manifest.json        spec, seed, sizes, versions, file list, content hash
      grid/                the bench's N × M PSF grid in psfkit's grid format (+ ground_truth/):
                           ``psfkit fit-eigen root/grid`` gives the eigen-kernel seed model
      train/scene/*.npy    ground-truth scenes (H', W', 3) float32 in [0, 1], RGB
      train/measurement/*.npy   simulated measurements (H', W', 3) float32
      test/...             held-out scenes (other natural images, other dead-leaves seeds)
      oracle/              the best paper-basis eigen-kernel models, both conventions
                           (:mod:`ekdun.data.oracle`): ``paper_{source,sensor}.npz`` (operator
                           oracle) and ``psf_paper_{source,sensor}.npz`` (PSF oracle)

Scenes: dead-leaves images (:mod:`ekdun.data.deadleaves`) and random crops of the natural
images that ship inside scikit-image (different images for train and test). Measurements:
the DENSE shift-variant model (:mod:`ekdun.data.dense_model`) built from the noise-free bench
PSFs of every grid node (re-centred on their chief rays), with Poisson–Gaussian sensor noise
— never the eigen-kernel model that the networks use, so that the comparison of forward models
is meaningful. The folders ``train/`` and ``test/`` are ordinary pairs folders
(:func:`psfkit.io.pairs.read_pairs`).

Everything is deterministic given ``spec.seed``; a folder whose manifest matches the spec
(and whose content hash checks) is reused, one whose manifest disagrees is rebuilt, and a
non-empty folder that is not a virtual-bench dataset is refused.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ekdun.data.deadleaves import dead_leaves
from ekdun.data.dense_model import DenseShiftVariantModel
from ekdun.errors import ConfigurationError, InvalidInputError
from psfkit.bench import BenchConfig, simulate_grid
from psfkit.bench.camera import VirtualCamera, place_patch
from psfkit.bench.simulate import grid_monitor_positions
from psfkit.io.atomic import atomic_directory, atomic_file
from psfkit.io.images import write_image
from psfkit.validation import read_json_file

FORMAT = "ekdun-virtual-bench"
VERSION = 1
MANIFEST = "manifest.json"
TRAIN_IMAGES = ("astronaut", "coffee", "chelsea", "immunohistochemistry", "camera", "coins",
                "brick", "grass", "moon")
TEST_IMAGES = ("rocket", "gravel", "clock", "hubble_deep_field")
FULL_PIXEL_UM = 3.45


@dataclass(frozen=True)
class VirtualBenchSpec:
    """What a virtual-bench dataset contains (everything that changes its bytes).

    Attributes
    ----------
    sensor_shape : (int, int)
        ``(H', W')`` of scenes and measurements.
    n_train, n_test : int
        Numbers of pairs.
    grid_shape : (int, int)
        Field points of the simulated PSF grid (and nodes of the dense model), ≥ 9 × 9.
    half_fov_deg : float
        Field angle at the sensor's horizontal edge: the bench geometry (diffuser–sensor gap)
        is chosen so that the grid's outermost points land on the sensor edges. Wide fields of
        view make the PSF vary strongly (vignetting ``cos⁴θ``, oblique-incidence
        astigmatism, shrinking projected aperture).
    monitor_distance_mm : float
        Distance of the (virtual) display.
    aperture_mm : float
        Side of the square aperture in front of the diffuser (sets the PSF's extent on the
        sensor: 1.3 mm covers about 37 % of the width of the default 3.5 mm sensor, a
        better-conditioned camera than 2.6 mm, which covers 3/4 of it).
    binning : int
        Sensor binning of the bench (full-resolution sensor = ``binning × sensor_shape`` of
        3.45 µm pixels).
    natural_fraction : float
        Fraction of scenes cropped from scikit-image's natural images (rest: dead leaves).
    photons : float
        Photo-electrons for a measurement value of 1 (Poisson noise).
    read_noise_e : float
        Gaussian read noise (electrons).
    convention : {"source", "sensor"}
        Where the dense model's interpolation weights act.
    seed : int
        Seed of the diffuser, scenes and noise.
    oracle : bool
        Also write the eigen-kernel oracles (paper basis, both conventions) under
        ``oracle/`` (:mod:`ekdun.data.oracle`).
    oracle_scenes : int
        Scenes of the operator oracle (0: :func:`ekdun.data.oracle.default_oracle_scenes`).
    """

    sensor_shape: tuple[int, int] = (64, 64)
    n_train: int = 96
    n_test: int = 24
    grid_shape: tuple[int, int] = (9, 9)
    half_fov_deg: float = 30.0
    monitor_distance_mm: float = 200.0
    aperture_mm: float = 1.3
    binning: int = 16
    natural_fraction: float = 0.5
    photons: float = 2000.0
    read_noise_e: float = 2.0
    convention: str = "source"
    seed: int = 0
    oracle: bool = True
    oracle_scenes: int = 0

    def __post_init__(self) -> None:
        if min(self.grid_shape) < 3:
            raise ConfigurationError("grid_shape must be at least 3 x 3 (9 x 9 recommended)")
        if min(self.sensor_shape) < 16 or self.n_train < 1 or self.n_test < 1:
            raise ConfigurationError("sensor_shape must be >= 16 px and n_train, n_test >= 1")
        if not 0 < self.half_fov_deg < 60:
            raise ConfigurationError("half_fov_deg must be in (0, 60)")
        if not 0 <= self.natural_fraction <= 1:
            raise ConfigurationError("natural_fraction must be in [0, 1]")

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self)))

    def bench_config(self) -> BenchConfig:
        """The virtual camera: grid edge points at ±``half_fov_deg`` land on the sensor edges."""
        h, w = self.sensor_shape
        half_w_mm = w * self.binning * FULL_PIXEL_UM * 1e-3 / 2
        gap_mm = half_w_mm / math.tan(math.radians(self.half_fov_deg))
        half_h_mm = h * self.binning * FULL_PIXEL_UM * 1e-3 / 2
        pitch = BenchConfig().monitor_pixel_pitch_mm
        fov = tuple(round(2 * self.monitor_distance_mm * half / gap_mm / pitch)
                    for half in (half_h_mm, half_w_mm))
        return BenchConfig(sensor_shape=(h * self.binning, w * self.binning),
                           downsample=self.binning, gap_mm=gap_mm,
                           monitor_distance_mm=self.monitor_distance_mm,
                           aperture_mm=(self.aperture_mm, self.aperture_mm),
                           fov_monitor_px=fov, seed=self.seed)


def _versions() -> dict[str, str]:
    import numpy
    import skimage

    from ekdun import __version__ as ekdun_version
    return {"format": f"{FORMAT}/{VERSION}", "ekdun": ekdun_version, "numpy": numpy.__version__,
            "torch": torch.__version__.split("+")[0], "scikit-image": skimage.__version__}


def node_psfs(spec: VirtualBenchSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The bench's noise-free node PSFs and where they land (what the dense model is built of).

    Returns
    -------
    kernels : numpy.ndarray
        ``(N, M, C, H', W')`` float64: each node's PSF re-centred on its chief ray (origin at
        the array centre), in measurement units per unit scene radiance (QE colour balance).
    shifts : numpy.ndarray
        ``(N, M, 2)``: the true chief-ray shift ``(du, dv)`` of each node from the sensor
        centre, in sensor pixels (same node order as ``kernels``).
    rows, cols : numpy.ndarray
        Sensor row coordinates of the node rows and column coordinates of the node columns,
        increasing (the node order is reversed where the optics flip the image).
    """
    config = spec.bench_config()
    camera = VirtualCamera(config)
    monitor = grid_monitor_positions(config, spec.grid_shape)
    fx, fy = camera.field_from_monitor(monitor[..., 0], monitor[..., 1])
    h, w = camera.sensor_shape
    qe = config.sensor.qe(len(camera.channels))
    qe = (qe / qe.mean())[:, None, None]
    n, m = spec.grid_shape
    kernels = np.zeros((n, m, len(camera.channels), h, w), dtype=np.float64)
    shifts = np.zeros((n, m, 2))
    for r in range(n):
        for c in range(m):
            field = (float(fx[r, c]), float(fy[r, c]))
            patch = camera.psf_patch(field, subpixel_shift=False)
            bh, bw = patch.image.shape[-2:]
            centred = type(patch)(image=patch.image, offset=((h - bh) // 2, (w - bw) // 2),
                                  shift_px=(0.0, 0.0))
            kernels[r, c] = place_patch(centred, (h, w)) * qe
            shifts[r, c] = camera.true_shift_px(field)
    rows = h // 2 + shifts[:, :, 1].mean(axis=1)
    cols = w // 2 + shifts[:, :, 0].mean(axis=0)
    # A source at +x (+y) images to -u (-v): node order is reversed on the sensor.
    if rows[0] > rows[-1]:
        rows, kernels, shifts = rows[::-1], kernels[::-1], shifts[::-1]
    if cols[0] > cols[-1]:
        cols, kernels, shifts = cols[::-1], kernels[:, ::-1], shifts[:, ::-1]
    return kernels, shifts, rows, cols


def dense_model_for(spec: VirtualBenchSpec) -> DenseShiftVariantModel:
    """The dense forward model of the spec's bench (noise-free node PSFs, QE colour balance)."""
    kernels, _shifts, rows, cols = node_psfs(spec)
    return DenseShiftVariantModel(kernels, rows, cols, spec.sensor_shape, spec.convention)


def _natural_crop(name: str, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    import skimage.data
    from skimage.transform import resize

    image = np.asarray(getattr(skimage.data, name)(), dtype=np.float64)
    if image.max() > 1:
        image = image / 255.0
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    image = image[..., :3]
    ih, iw = image.shape[:2]
    aspect = shape[1] / shape[0]
    side = rng.uniform(0.3, 1.0) * min(ih, iw / aspect)
    ch, cw = int(side), int(side * aspect)
    y0, x0 = rng.integers(0, ih - ch + 1), rng.integers(0, iw - cw + 1)
    crop = image[y0:y0 + ch, x0:x0 + cw]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    out = resize(crop, shape, order=1, anti_aliasing=True)
    return np.clip(np.moveaxis(out, -1, 0), 0, 1).astype(np.float32)


def make_scenes(spec: VirtualBenchSpec, split: str, count: int | None = None,
                stream: int | None = None) -> np.ndarray:
    """``(N, 3, H', W')`` float32 scenes of ``split`` (``"train"`` or ``"test"``).

    ``count`` scenes (default the split's size) from random stream ``stream`` (default the
    split's own: 0 train, 1 test); another stream draws new scenes of the same distribution
    (the oracle's, :mod:`ekdun.data.oracle`).
    """
    n = (spec.n_train if split == "train" else spec.n_test) if count is None else count
    names = TRAIN_IMAGES if split == "train" else TEST_IMAGES
    split_id = (0 if split == "train" else 1) if stream is None else stream
    out = np.empty((n, 3, *spec.sensor_shape), dtype=np.float32)
    for i in range(n):
        rng = np.random.default_rng([spec.seed, split_id, i])
        if rng.random() < spec.natural_fraction:
            out[i] = _natural_crop(names[int(rng.integers(len(names)))], spec.sensor_shape, rng)
        else:
            out[i] = dead_leaves(spec.sensor_shape, rng)
    return out


def simulate_measurements(model: DenseShiftVariantModel, scenes: np.ndarray,
                          spec: VirtualBenchSpec, split_id: int, batch: int = 8) -> np.ndarray:
    """Noisy measurements of ``scenes`` (Poisson–Gaussian, deterministic by seed)."""
    out = np.empty_like(scenes)
    for start in range(0, len(scenes), batch):
        clean = model(torch.as_tensor(scenes[start:start + batch])).numpy()
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
    """The pairs folder of ``data``: a virtual-bench dataset root means its ``split``
    folder (``"train"`` or ``"test"``), anything else is a pairs folder itself.

    Raises
    ------
    InvalidInputError
        ``data`` is not a folder.
    """
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
    if doc is None or doc.get("spec") != spec.to_dict() or doc.get("versions") != _versions():
        return False
    files = _data_files(root)
    if files != doc.get("files"):
        return False
    return not verify_hash or content_hash(root, files) == doc.get("content_hash")


def make_virtual_bench(root: str | os.PathLike, spec: VirtualBenchSpec | None = None,
                       progress: bool = True, verify_hash: bool = True) -> Path:
    """Build the dataset at ``root`` unless an identical one is already there.

    Parameters
    ----------
    root : path-like
        Dataset folder (created atomically).
    spec : VirtualBenchSpec
        Contents (default: the ``tiny`` dataset).
    progress : bool
        Progress bars.
    verify_hash : bool
        Re-hash the files of an existing dataset before reusing it.

    Returns
    -------
    pathlib.Path

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
                      suffix=".npy", progress=progress)
        model = dense_model_for(spec)
        for split_id, split in enumerate(("train", "test")):
            scenes = make_scenes(spec, split)
            measurements = simulate_measurements(model, scenes, spec, split_id)
            for sub, arrays in (("scene", scenes), ("measurement", measurements)):
                folder = tmp / split / sub
                folder.mkdir(parents=True)
                for i, image in enumerate(arrays):
                    # the one image writer: refuses NaN/Inf (e.g. --photons 1e-300)
                    write_image(folder / f"{split}{i:04d}.npy", image.astype(np.float32))
        oracle = None
        if spec.oracle:
            from ekdun.data.oracle import write_oracles

            oracle = write_oracles(tmp / "oracle", spec, n_scenes=spec.oracle_scenes or None)
        files = _data_files(tmp)
        manifest = {
            "format": FORMAT, "version": VERSION, "spec": spec.to_dict(),
            "versions": _versions(), "bench": spec.bench_config().to_dict(),
            "forward_model": f"dense bilinear interpolation of {spec.grid_shape[0]}x"
                             f"{spec.grid_shape[1]} noise-free bench PSFs ({spec.convention} "
                             "weights) + Poisson-Gaussian noise",
            "files": files, "content_hash": content_hash(tmp, files),
        }
        if oracle is not None:
            manifest["oracle"] = oracle
        with atomic_file(tmp / MANIFEST) as out:
            out.write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return root
