"""The virtual bench's camera, scenes and dense forward model (what a dataset is made of):
:class:`VirtualBenchSpec`, :func:`node_psfs`, :func:`dense_model_for` and :func:`make_scenes`.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ekdun.data.deadleaves import dead_leaves
from ekdun.data.dense_model import DenseShiftVariantModel
from ekdun.errors import ConfigurationError, InvalidInputError
from ekdun.flag_ranges import flag_range
from psfkit.simulate import BenchConfig
from psfkit.simulate.camera import VirtualCamera
from psfkit.simulate.psf_grid import grid_monitor_positions
from psfkit.simulate.psf_patch import place_patch

TRAIN_IMAGES = ("astronaut", "coffee", "chelsea", "immunohistochemistry", "camera", "coins",
                "brick", "grass", "moon")
TEST_IMAGES = ("rocket", "gravel", "clock", "hubble_deep_field")
FULL_PIXEL_UM = 3.45
#: Fields of older manifests that no longer change a dataset's bytes (the eigen-kernel
#: oracles, which ``research/oracles.py`` writes, not ``make-dataset``): ignored
#: when read, so that those datasets stay readable and are still reused.
RETIRED_FIELDS = ("oracle", "oracle_scenes")


@dataclass(frozen=True)
class VirtualBenchSpec:
    """What a virtual-bench dataset contains (everything that changes its bytes).

    Attributes
    ----------
    sensor_shape : (int, int)
        ``(H', W')`` of scenes and measurements.
    n_train, n_test : int
    grid_shape : (int, int)
        Field points of the simulated PSF grid (and nodes of the dense model).
    half_fov_deg : float
        Field angle at the sensor's horizontal edge (sets the diffuser–sensor gap).
    monitor_distance_mm : float
    aperture_mm : float
        Side of the square aperture in front of the diffuser (the PSF's extent).
    binning : int
        Sensor binning (full-resolution sensor: ``binning × sensor_shape`` of 3.45 µm pixels).
    natural_fraction : float
        Fraction of scenes cropped from scikit-image's natural images (rest: dead leaves).
    photons : float
        Photo-electrons for a measurement value of 1 (Poisson noise).
    read_noise_e : float
        Gaussian read noise (electrons) of the pairs.
    grid_frames : int
        Frames averaged at each position of the PSF grid (the pairs are unchanged).
    convention : {"source", "sensor"}
        Where the dense model's interpolation weights act.
    seed : int
        Seed of the diffuser, scenes and noise.
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
    grid_frames: int = 1
    convention: str = "source"
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.grid_shape) < 3:
            raise ConfigurationError("grid_shape must be at least 3 x 3 (9 x 9 recommended)")
        if min(self.sensor_shape) < 16 or self.n_train < 1 or self.n_test < 1:
            raise ConfigurationError("sensor_shape must be >= 16 px and n_train, n_test >= 1")
        if not 0 < self.half_fov_deg < 60:
            raise ConfigurationError("half_fov_deg must be in (0, 60)")
        if not 0 <= self.natural_fraction <= 1:
            raise ConfigurationError("natural_fraction must be in [0, 1]")
        try:   # the range of --photons (one table)
            flag_range("--photons").check(self.photons, "photons (--photons)")
        except InvalidInputError as exc:
            raise ConfigurationError(str(exc)) from None
        if isinstance(self.grid_frames, bool) or int(self.grid_frames) != self.grid_frames \
                or self.grid_frames < 1:
            raise ConfigurationError(f"grid_frames must be an integer >= 1, got "
                                     f"{self.grid_frames!r}")

    def to_dict(self) -> dict[str, Any]:
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> VirtualBenchSpec:
        """The spec of :meth:`to_dict` (JSON lists back to tuples)."""
        values = {k: v for k, v in doc.items() if k not in RETIRED_FIELDS}
        for key in ("sensor_shape", "grid_shape"):
            if key in values:
                values[key] = tuple(values[key])
        return cls(**values)

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


def node_psfs(spec: VirtualBenchSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The bench's noise-free node PSFs and where they land.

    Returns
    -------
    kernels : numpy.ndarray
        ``(N, M, C, H', W')`` float64: each node's PSF centred on its chief ray, in measurement
        units per unit scene radiance (QE colour balance).
    shifts : numpy.ndarray
        ``(N, M, 2)``: the chief-ray shift ``(du, dv)`` of each node from the sensor centre, px.
    rows, cols : numpy.ndarray
        Increasing sensor coordinates of the node rows and columns.
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


@functools.cache
def _natural_image(name: str) -> np.ndarray:
    """``skimage.data.<name>()`` as read-only ``(H, W, 3)`` float64 in [0, 1], cached."""
    import skimage.data

    image = np.asarray(getattr(skimage.data, name)(), dtype=np.float64)
    if image.max() > 1:
        image = image / 255.0
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    image = np.ascontiguousarray(image[..., :3])
    image.flags.writeable = False
    return image


def _natural_crop(name: str, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    from skimage.transform import resize

    image = _natural_image(name)
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


def _scene(spec: VirtualBenchSpec, names: tuple[str, ...], split_id: int, i: int
           ) -> np.ndarray:
    """Scene ``i`` of random stream ``split_id``: its own generator, so any process draws it."""
    rng = np.random.default_rng([spec.seed, split_id, i])
    if rng.random() < spec.natural_fraction:
        return _natural_crop(names[int(rng.integers(len(names)))], spec.sensor_shape, rng)
    return dead_leaves(spec.sensor_shape, rng)


def _scene_chunk(spec: VirtualBenchSpec, names: tuple[str, ...], split_id: int,
                 indices: range) -> np.ndarray:
    return np.stack([_scene(spec, names, split_id, i) for i in indices])


def make_scenes(spec: VirtualBenchSpec, split: str, count: int | None = None,
                stream: int | None = None, workers: int = 1,
                progress: bool = False) -> np.ndarray:
    """``(N, 3, H', W')`` float32 scenes of ``split`` (``"train"`` or ``"test"``).

    ``count`` scenes (default the split's size) from random stream ``stream`` (default 0 for
    train, 1 for test); ``workers`` processes draw them, each scene from its own seed, so the
    result does not depend on ``workers``.
    """
    n = (spec.n_train if split == "train" else spec.n_test) if count is None else count
    names = TRAIN_IMAGES if split == "train" else TEST_IMAGES
    split_id = (0 if split == "train" else 1) if stream is None else stream
    out = np.empty((n, 3, *spec.sensor_shape), dtype=np.float32)
    workers = max(1, min(int(workers), n))
    from tqdm.auto import tqdm

    bar = tqdm(total=n, desc=f"scenes ({split})", unit="scene", disable=not progress)
    step = 1 if workers == 1 else max(1, -(-n // (4 * workers)))
    chunks = [range(a, min(a + step, n)) for a in range(0, n, step)]
    draw = functools.partial(_scene_chunk, spec, names, split_id)
    # spawn, not fork: the parent may already hold torch's OpenMP threads
    pool = (ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
            if workers > 1 else None)
    with pool or contextlib.nullcontext():
        drawn = map(draw, chunks) if pool is None else pool.map(draw, chunks)
        for chunk, images in zip(chunks, drawn, strict=True):
            out[chunk.start:chunk.stop] = images
            bar.update(len(chunk))
    bar.close()
    return out
