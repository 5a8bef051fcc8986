"""Simulate a measured PSF grid with the virtual bench, with its ground truth.

:func:`simulate_grid` does what a lab does: a point displayed at N × M monitor positions, each
captured with one fixed exposure (vignetting stays visible; optionally averaged over
``frames``), written in the grid format with a dark frame. In ``ground_truth/`` it adds what a
lab cannot know: ``truth.json`` (per position the field angles, true chief-ray shift
``(du, dv)`` relative to the on-axis PSF, gain and saturated pixel count; the bench, exposure
and frames) and, optionally, ``psfs_clean.npy`` (``(N, M, C, H, W)`` float32 noise-free signal
above black level in file units, memory-mapped). Without it :func:`read_ground_truth`
recomputes the clean PSFs on request (:class:`CleanPsfs`).
"""

from __future__ import annotations

import json
import os
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.io.grid_writer import GridWriter
from psfkit.io.json_documents import read_json_file
from psfkit.simulate.bench_config import BenchConfig
from psfkit.simulate.camera import VirtualCamera

TRUTH_DIR = "ground_truth"
CLEAN_FILE = "psfs_clean.npy"
NOMINAL_EXPOSURE_S = 0.01


def grid_monitor_positions(config: BenchConfig, grid_shape: tuple[int, int],
                           extent: float = 1.0) -> np.ndarray:
    """Monitor positions ``(x, y)`` (pixels from the axis) of an N × M grid, ``(N, M, 2)``.

    Evenly spaced over ``extent`` times the field of view; an odd grid has its middle on the axis.
    """
    n_rows, n_cols = grid_shape
    if n_rows < 1 or n_cols < 1:
        raise ConfigurationError(f"grid shape must be positive, got {grid_shape}")
    if not 0 < extent <= 2:
        raise ConfigurationError(f"extent must be in (0, 2], got {extent}")
    fov_h, fov_w = config.fov_monitor_px
    xs = np.linspace(-0.5, 0.5, n_cols) * fov_w * extent if n_cols > 1 else np.zeros(1)
    ys = np.linspace(-0.5, 0.5, n_rows) * fov_h * extent if n_rows > 1 else np.zeros(1)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack([xx, yy], axis=-1)


def _optics_threads(camera: VirtualCamera) -> AbstractContextManager[None]:
    """One torch thread for a torch-backend CPU camera during a grid: the FFTs run in scipy on all
    cores, and a second OpenMP thread costs far more than it gains next to the writer thread."""
    if camera.backend == "torch" and camera.device_type == "cpu":
        from psfkit.simulate.propagation_torch import cpu_threads

        return cpu_threads(1)
    return nullcontext()


def exposure_scale(camera: VirtualCamera, on_axis_psf: np.ndarray) -> float:
    """Photo-electrons per unit relative irradiance for the grid's one exposure: the brightest
    on-axis pixel (after quantum efficiency) reaches ``peak_fraction`` of full well."""
    cfg = camera.config
    qe = cfg.sensor.qe(on_axis_psf.shape[0])
    peak = float(np.max(on_axis_psf.reshape(on_axis_psf.shape[0], -1).max(axis=1) * qe))
    return cfg.peak_fraction * cfg.sensor.full_well_e / peak


def simulate_grid(out_dir: str | os.PathLike, config: BenchConfig | None = None,
                  grid_shape: tuple[int, int] = (9, 9), extent: float = 1.0,
                  dark_frame: bool = True, suffix: str = ".tiff", overwrite: bool = False,
                  progress: bool = True, backend: str = "numpy", frames: int = 1,
                  clean_psfs: bool = True, run_file: dict[str, Any] | None = None) -> Path:
    """Simulate and write a PSF grid with ground truth (see the module docstring).

    Parameters
    ----------
    out_dir : path-like
        Destination folder (created atomically).
    config : BenchConfig, optional
        Default: the paper-like full-resolution camera.
    grid_shape : (int, int)
        Rows × columns of source positions.
    extent : float
        Fraction of the field of view spanned.
    dark_frame : bool
        Also capture a dark frame.
    suffix : {".tiff", ".png", ".npy"}
    overwrite, progress : bool
        Replace an existing output folder; show a progress bar.
    backend : {"numpy", "torch", "auto"}
        Optics backend: ``"numpy"`` reproduces existing grids file for file; ``"torch"`` is
        faster, with clean PSFs equal to ~5e-7 relative but another noise realization.
    frames : int
        Frames averaged per position and dark frame; above 1 the float32 mean is written.
    clean_psfs : bool
        Write ``ground_truth/psfs_clean.npy``; otherwise they are recomputed when read.
    run_file : dict, optional
        A ``--config`` run file's settings, recorded under ``simulation.run_file``.

    Returns
    -------
    pathlib.Path
        The grid folder.
    """
    config = config or BenchConfig()
    monitor = grid_monitor_positions(config, grid_shape, extent)
    return _simulate(out_dir, config, monitor, False, dark_frame, suffix, overwrite, progress,
                     backend, frames, clean_psfs, run_file)


def simulate_scan(out_dir: str | os.PathLike, monitor_px: np.ndarray,
                  config: BenchConfig | None = None, dark_frame: bool = True,
                  suffix: str = ".tiff", overwrite: bool = False, progress: bool = True,
                  backend: str = "numpy", frames: int = 1) -> Path:
    """Simulate an irregular scan: the point source at the given monitor positions, written as a
    grid folder without grid indices (a ``1 × P`` row), ground truth as :func:`simulate_grid`.
    Include ``(0, 0)`` for the reference PSF.

    Parameters
    ----------
    monitor_px : numpy.ndarray
        ``(P, 2)`` source positions ``(x, y)`` in monitor pixels from the optical axis.
    Other parameters as :func:`simulate_grid`.
    """
    config = config or BenchConfig()
    monitor = np.asarray(monitor_px, dtype=np.float64)
    if monitor.ndim != 2 or monitor.shape[1] != 2 or len(monitor) < 1:
        raise ConfigurationError(f"monitor_px must be (P, 2), got {monitor.shape}")
    return _simulate(out_dir, config, monitor[None], True, dark_frame, suffix, overwrite,
                     progress, backend, frames)


def _checked_frames(frames: int, suffix: str) -> int:
    """The frames averaged per position: an integer >= 1, and 1 for PNG (a mean is float data)."""
    if isinstance(frames, bool) or int(frames) != frames or frames < 1:
        raise ConfigurationError(f"frames must be an integer >= 1, got {frames!r}")
    if frames > 1 and suffix == ".png":
        raise ConfigurationError("an average of several frames is float data: write it as "
                                 "TIFF or .npy, not PNG")
    return int(frames)


def _grid_header(config: BenchConfig, frames: int, run_file: dict[str, Any] | None
                 ) -> dict[str, Any]:
    """The simulated grid's header fields: sensor, monitor and how it was simulated."""
    header: dict[str, Any] = {
        "bit_depth": config.sensor.bit_depth,
        "black_level": config.sensor.black_level,
        "monitor": {"distance_mm": config.monitor_distance_mm,
                    "pixel_pitch_mm": config.monitor_pixel_pitch_mm},
        "simulation": {"generator": "psfkit virtual bench", "seed": config.seed,
                       "ground_truth": TRUTH_DIR},
    }
    if frames > 1:
        header["simulation"]["frames_averaged"] = frames
    if run_file is not None:
        header["simulation"]["run_file"] = run_file
    return header


def _simulate(out_dir: str | os.PathLike, config: BenchConfig, monitor: np.ndarray,
              scan: bool, dark_frame: bool, suffix: str, overwrite: bool, progress: bool,
              backend: str, frames: int, write_clean: bool = True,
              run_file: dict[str, Any] | None = None) -> Path:
    """:func:`simulate_grid` and :func:`simulate_scan` at ``(N, M, 2)`` monitor positions."""
    frames = _checked_frames(frames, suffix)
    n_rows, n_cols = grid_shape = monitor.shape[:2]
    sensor = config.sensor
    header = _grid_header(config, frames, run_file)
    truth_positions = []
    # Enter the writer first: an existing output folder is reported before any work.
    with GridWriter(out_dir, None if scan else grid_shape, suffix=suffix, overwrite=overwrite,
                    **header) as writer:
        camera = VirtualCamera(config, backend=backend)
        writer.header["pixel_pitch_um"] = camera.pixel_um
        fx, fy = camera.field_from_monitor(monitor[..., 0], monitor[..., 1])
        fields_deg = np.stack([fx, fy], axis=-1)
        qe = sensor.qe(len(camera.channels))[:, None, None]
        noise_rng = np.random.default_rng([config.seed, 1])

        def capture(electrons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """One raw frame (uint16) or the mean of ``frames``, and its saturated pixels."""
            if frames == 1:
                raw = sensor.capture(electrons, noise_rng)
                return raw, raw >= sensor.max_dn * sensor.container_scale
            return sensor.capture_mean(electrons, noise_rng, frames)
        h, w = camera.sensor_shape
        truth_dir = writer.folder / TRUTH_DIR
        truth_dir.mkdir()
        clean = np.lib.format.open_memmap(
            truth_dir / CLEAN_FILE, mode="w+", dtype=np.float32,
            shape=(n_rows, n_cols, len(camera.channels), h, w)) if write_clean else None
        indices = [(r, c) for r in range(n_rows) for c in range(n_cols)]
        iterator: Any = indices
        if progress:
            from tqdm.auto import tqdm

            iterator = tqdm(indices, desc="simulating PSF grid", unit="psf")

        def finish(r: int, c: int, field: tuple[float, float], electrons: np.ndarray,
                   clean: np.ndarray | None) -> None:
            """Capture, write and record one position (in order: the noise stream is shared)."""
            raw, saturated = capture(electrons)
            if clean is not None:
                clean[r, c] = sensor.expected_file_units(electrons)   # as CleanPsfs computes it
            fields = {"monitor_px": tuple(monitor[r, c]), "field_deg": field,
                      "exposure_s": NOMINAL_EXPOSURE_S}
            if scan:
                writer.add_scan(c, raw, **fields)
            else:
                writer.add(r, c, raw, **fields)
            du, dv = camera.true_shift_px(field)
            truth_positions.append({
                "row": r, "col": c, "field_deg": list(field),
                "monitor_px": [float(v) for v in monitor[r, c]],
                "shift_px": [du, dv], "gain": camera.gain(field),
                "saturated_pixels": int(np.count_nonzero(saturated)),
            })

        # the noise, the files and the optics of the next position overlap: one writer thread,
        # at most one position waiting for it (bounded memory, same order, same noise)
        with _optics_threads(camera), ThreadPoolExecutor(max_workers=1) as pool:
            electrons_per_unit = exposure_scale(camera, camera.psf((0.0, 0.0)))
            pending: Future[None] | None = None
            for r, c in iterator:
                field = (float(fields_deg[r, c, 0]), float(fields_deg[r, c, 1]))
                electrons = camera.psf(field) * (electrons_per_unit * qe)
                if pending is not None:
                    pending.result()
                pending = pool.submit(finish, r, c, field, electrons, clean)
            if pending is not None:
                pending.result()
        if clean is not None:
            clean.flush()
        del clean
        if dark_frame:
            writer.add_dark(capture(np.zeros((len(camera.channels), h, w)))[0])
        truth = {
            "description": "virtual-bench ground truth; shifts are (du, dv) in sensor pixels "
                           "of each PSF relative to the on-axis PSF (a source at +x moves its "
                           "PSF to -u); gain is the relative illumination (1 on axis)",
            "grid_shape": [n_rows, n_cols],
            "layout": "irregular" if scan else "full lattice",
            "channels": list(camera.channels),
            "sensor_shape": [h, w],
            "pixel_pitch_um": camera.pixel_um,
            "gap_um": camera.gap_um,
            "magnification_px_per_monitor_px": camera.magnification,
            "electrons_per_unit_irradiance": electrons_per_unit,
            "file_units_per_electron": sensor.container_scale / sensor.electrons_per_dn,
            "black_level": sensor.black_level,
            "frames_averaged": frames,
            "oversample": camera.oversample,
            "correlation_length_um": camera.correlation_length_um,
            "backend": camera.backend,
            "clean_psfs": CLEAN_FILE if write_clean else "recomputed on request",
            "config": config.to_dict(),
            "positions": truth_positions,
        }
        (truth_dir / "truth.json").write_text(json.dumps(truth, indent=1) + "\n",
                                              encoding="utf-8")
    return Path(out_dir)


class CleanPsfs:
    """The noise-free PSFs of a grid without ``psfs_clean.npy``, recomputed from the bench in
    ``truth.json`` exactly as :func:`simulate_grid` did (bit for bit with the numpy backend).

    Reads like the ``(N, M, C, H, W)`` float32 array: ``clean[r, c]`` simulates one position; any
    other index, or ``np.asarray``, builds the whole array.
    """

    dtype = np.dtype(np.float32)

    def __init__(self, info: dict[str, Any], config: BenchConfig, field_deg: np.ndarray) -> None:
        h, w = info["sensor_shape"]
        self.shape = (*field_deg.shape[:2], len(info["channels"]), int(h), int(w))
        self.ndim = len(self.shape)
        self._info, self._config, self._field_deg = info, config, field_deg
        self._camera: VirtualCamera | None = None

    def __len__(self) -> int:
        return self.shape[0]

    def psf(self, row: int, col: int) -> np.ndarray:
        """``(C, H, W)`` float32 clean PSF of grid position ``(row, col)`` (file units)."""
        if self._camera is None:
            self._camera = VirtualCamera(self._config, backend=self._info.get("backend", "numpy"))
        sensor = self._config.sensor
        qe = sensor.qe(self.shape[2])[:, None, None]
        field = (float(self._field_deg[row, col, 0]), float(self._field_deg[row, col, 1]))
        electrons = self._camera.psf(field) * (self._info["electrons_per_unit_irradiance"] * qe)
        return sensor.expected_file_units(electrons).astype(np.float32)

    def __getitem__(self, index: Any) -> np.ndarray:
        if (isinstance(index, tuple) and len(index) == 2
                and all(isinstance(i, (int, np.integer)) for i in index)):
            row, col = (int(i) % n for i, n in zip(index, self.shape[:2], strict=True))
            return self.psf(row, col)
        return np.asarray(self)[index]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        out = np.empty(self.shape, np.float32)
        for row in range(self.shape[0]):
            for col in range(self.shape[1]):
                out[row, col] = self.psf(row, col)
        return out if dtype is None else out.astype(dtype)


@dataclass(frozen=True)
class GroundTruth:
    """Ground truth of a simulated grid (:func:`read_ground_truth`).

    Indexed ``[row, col]``: ``field_deg`` ``(θx, θy)`` and ``shift_px`` ``(du, dv)`` are
    ``(N, M, 2)``, ``gain`` ``(N, M)``; ``clean_psfs`` the ``(N, M, C, H, W)`` noise-free signal
    above black level (file units), memory-mapped or a :class:`CleanPsfs`.
    """

    field_deg: np.ndarray
    monitor_px: np.ndarray
    shift_px: np.ndarray
    gain: np.ndarray
    clean_psfs: np.ndarray | CleanPsfs
    config: BenchConfig
    info: dict[str, Any]


def read_ground_truth(grid_dir: str | os.PathLike) -> GroundTruth:
    """Load the ground truth written by :func:`simulate_grid` next to a grid."""
    folder = Path(grid_dir) / TRUTH_DIR
    truth_file = folder / "truth.json"
    if not truth_file.is_file():
        raise InvalidInputError(f"{grid_dir}: no {TRUTH_DIR}/truth.json (not a simulated grid)")
    info = read_json_file(truth_file)
    n_rows, n_cols = info["grid_shape"]

    def table(key: str) -> np.ndarray:
        by_index = {(p["row"], p["col"]): p[key] for p in info["positions"]}
        values = np.array([by_index[(r, c)] for r in range(n_rows) for c in range(n_cols)],
                          dtype=np.float64)
        return values.reshape(n_rows, n_cols, *values.shape[1:])

    field_deg, config = table("field_deg"), BenchConfig.from_dict(info["config"])
    clean_file = folder / CLEAN_FILE
    clean = (np.load(clean_file, mmap_mode="r") if clean_file.is_file()
             else CleanPsfs(info, config, field_deg))
    return GroundTruth(
        field_deg=field_deg, monitor_px=table("monitor_px"),
        shift_px=table("shift_px"), gain=table("gain"), clean_psfs=clean,
        config=config, info=info)
