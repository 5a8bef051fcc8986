"""A compact-PSF bench: a lens-like camera imaging point sources (stars, beads) at irregular,
known field positions, with its ground truth.

Written as an **irregular scan** in the grid format (``docs/grid-format.md``): one frame per
source with its field angles, the first on the optical axis (the reference). A source at
field angles ``θ`` images at ``x = c + A · tan θ`` (``c`` the axis on the sensor,
``A = −m R(ρ)``: magnification ``m`` px per unit ``tan θ``, an inverted image rotated by
``ρ``), plus an optional cubic radial distortion. Its PSF is a pixel-integrated Airy pattern
(``I(r) ∝ (2 J₁(kr)/kr)²``) of the given FWHM, optionally wider (``width_growth``) and
radially stretched (``1 + ellipticity``) at the field edge, both ∝ (field radius)², drawn
within ``STAMP_RADIUS_FWHM`` FWHMs. Sensor: :class:`~psfkit.simulate.sensor.SensorModel`
(mono); fluxes log-uniform over ``brightness_range``, the reference the brightest.

``ground_truth/truth.json`` records per position the field angles, true image position, true
shift ``(du, dv)`` relative to the reference, flux, FWHM, axis ratio and orientation, and the
camera; ``ground_truth/stamps.npy`` the noise-free unit-sum PSFs ``(P, S, S)``.
:func:`cutout_scan` writes the same scan as pre-centred cut-outs. A test facility, not a
command.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.io.grid_validation import read_grid
from psfkit.io.grid_writer import GridWriter
from psfkit.io.json_documents import read_json_file
from research.compact_bench.airy import airy_stamp
from research.compact_bench.camera import CompactCamera

TRUTH_DIR = "ground_truth"
TRUTH_FILE = "truth.json"
STAMPS_FILE = "stamps.npy"
#: Half-size of the drawn PSF stamp, in FWHMs of the widest PSF of the scan.
STAMP_RADIUS_FWHM = 10.0


@dataclass(frozen=True)
class CompactTruth:
    """Ground truth of a compact-PSF scan (:func:`read_compact_truth`).

    ``(P, 2)`` ``field_deg`` (θx, θy), ``position_px`` (true image ``(x, y)``, px) and
    ``shift_px`` (``(du, dv)`` relative to the reference); ``(P,)`` ``flux_e``, ``fwhm_px``,
    ``axis_ratio``; ``stamps`` ``(P, S, S)`` noise-free unit-sum PSFs; ``camera``; raw ``info``.
    """

    field_deg: np.ndarray
    position_px: np.ndarray
    shift_px: np.ndarray
    flux_e: np.ndarray
    fwhm_px: np.ndarray
    axis_ratio: np.ndarray
    stamps: np.ndarray
    camera: CompactCamera
    info: dict[str, Any]

    @property
    def frame_shape(self) -> tuple[int, int]:
        return tuple(self.info["frame_shape"])   # type: ignore[return-value]


def _positions(n: int, frame_shape: tuple[int, int], camera: CompactCamera,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Optical axis ``(x, y)`` and ``(P, 2)`` image positions: the axis, then uniform sources inside
    the margin."""
    h, w = frame_shape
    axis = np.array([(w - 1) / 2 + camera.axis_offset_px[0],
                     (h - 1) / 2 + camera.axis_offset_px[1]])
    margin = camera.edge_margin_px
    if min(h, w) <= 2 * margin + 2:
        raise ConfigurationError(f"frame {h}x{w} too small for an edge margin of {margin} px")
    xy = np.column_stack([rng.uniform(margin, w - 1 - margin, n - 1),
                          rng.uniform(margin, h - 1 - margin, n - 1)])
    return axis, np.vstack([axis, xy])


def _field_of(positions: np.ndarray, axis: np.ndarray, camera: CompactCamera,
              edge_radius: float) -> np.ndarray:
    """Field angles ``(P, 2)`` deg of sources imaging at ``positions``: the inverse affine map after
    removing the cubic distortion (fixed-point iteration)."""
    offset = positions - axis
    undistorted = offset.copy()
    k = camera.distortion_px / edge_radius**3
    for _ in range(50):           # r_d = r (1 + k r²): converges for |k| r² << 1
        r = np.hypot(*undistorted.T)[:, None]
        undistorted = offset / (1.0 + k * r**2)
    tan = undistorted @ np.linalg.inv(camera.shift_matrix()).T
    return np.degrees(np.arctan(tan))


def simulate_compact_scan(out_dir: str | os.PathLike, n_positions: int = 117,
                          frame_shape: tuple[int, int] = (1024, 1024),
                          camera: CompactCamera | None = None, seed: int = 0,
                          suffix: str = ".tiff", overwrite: bool = False,
                          progress: bool = False) -> Path:
    """Simulate an irregular scan of a compact (lens-like) PSF, with its ground truth.

    Parameters
    ----------
    out_dir : path-like
        Destination folder (written atomically).
    n_positions : int
        Sources, the on-axis reference included (≥ 3).
    frame_shape : (int, int)
        ``(H, W)`` of each frame, px.
    camera : CompactCamera, optional
        Default: a field-independent 3 px Airy PSF.
    seed : int
        Positions, brightnesses and noise.
    suffix : {".tiff", ".png", ".npy"}
        Image file type (16-bit raw frames).
    overwrite, progress : bool
        Replace an existing folder; show a progress bar.

    Returns
    -------
    pathlib.Path
        The scan folder.
    """
    camera = camera or CompactCamera()
    if n_positions < 3:
        raise ConfigurationError(f"n_positions must be >= 3, got {n_positions}")
    h, w = (int(frame_shape[0]), int(frame_shape[1]))
    rng = np.random.default_rng([seed, 43])
    axis, positions = _positions(n_positions, (h, w), camera, rng)
    edge_radius = math.hypot(w / 2, h / 2)
    fields = _field_of(positions, axis, camera, edge_radius)
    offset = positions - axis
    rho = np.hypot(*offset.T) / edge_radius                     # 0 on axis, 1 at the corner
    fwhm = camera.fwhm_px * (1.0 + camera.width_growth * rho**2)
    ratio = 1.0 + camera.ellipticity * rho**2
    orientation = np.arctan2(offset[:, 1], offset[:, 0])       # radial direction
    stamp_half = math.ceil(STAMP_RADIUS_FWHM * float(np.max(fwhm * ratio)))
    stamp_size = 2 * stamp_half + 1
    sensor = camera.sensor
    reference = airy_stamp(stamp_size, (stamp_half + 0.0, stamp_half + 0.0), fwhm[0])
    flux_max = camera.peak_fraction * sensor.full_well_e / float(reference.max())
    flux = flux_max / camera.brightness_range ** rng.uniform(0.0, 1.0, n_positions)
    flux[0] = flux_max
    stamps = np.zeros((n_positions, stamp_size, stamp_size), np.float32)
    records = []
    header = {"bit_depth": sensor.bit_depth, "black_level": sensor.black_level,
              "simulation": {"generator": "psfkit compact-PSF bench", "seed": seed,
                             "ground_truth": TRUTH_DIR}}
    indices: Any = range(n_positions)
    if progress:
        from tqdm.auto import tqdm

        indices = tqdm(indices, desc="simulating compact PSFs", unit="psf")
    with GridWriter(out_dir, None, suffix=suffix, overwrite=overwrite, **header) as writer:
        for p in indices:
            x, y = positions[p]
            ix, iy = round(float(x)), round(float(y))
            stamp = airy_stamp(stamp_size, (stamp_half + x - ix, stamp_half + y - iy),
                               fwhm[p], ratio[p], orientation[p])
            stamps[p] = stamp
            electrons = np.full((1, h, w), camera.background_e)
            _add_stamp(electrons[0], stamp * flux[p], ix - stamp_half, iy - stamp_half)
            writer.add_scan(p, sensor.capture(electrons, rng),
                            field_deg=tuple(float(v) for v in fields[p]))
            records.append({"index": p, "file": f"psf_{p:03d}{suffix}",
                            "field_deg": [float(v) for v in fields[p]],
                            "position_px": [float(x), float(y)],
                            "shift_px": [float(x - axis[0]), float(y - axis[1])],
                            "flux_e": float(flux[p]), "fwhm_px": float(fwhm[p]),
                            "axis_ratio": float(ratio[p]),
                            "orientation_deg": float(np.degrees(orientation[p])),
                            "stamp_corner_px": [ix - stamp_half, iy - stamp_half]})
        truth = {
            "description": "compact-PSF bench ground truth: position_px is the true image "
                           "position (x, y) of each source in its frame (pixel centres at "
                           "integers); shift_px (du, dv) = position − the reference's; the "
                           "true affine map shift = matrix · tan(field angle) (+ the cubic "
                           "distortion); stamps.npy holds the noise-free unit-sum PSFs, each "
                           "centred on pixel stamp_origin of its stamp at the integer part "
                           "of its position",
            "layout": "irregular", "frame_shape": [h, w], "n_positions": n_positions,
            "optical_axis_px": [float(v) for v in axis],
            "shift_matrix_px_per_tan": camera.shift_matrix().tolist(),
            "edge_radius_px": edge_radius, "stamp_size": stamp_size,
            "stamp_origin": [stamp_half, stamp_half],
            "electrons_per_file_unit": sensor.electrons_per_dn / sensor.container_scale,
            "camera": camera.to_dict(), "seed": seed, "crop": None, "positions": records,
        }
        _write_truth(writer.folder, stamps, truth)
    return Path(out_dir)


def _write_truth(folder: Path, stamps: np.ndarray, truth: dict[str, Any]) -> None:
    """``ground_truth/`` of a scan: the stamps and ``truth.json``."""
    truth_dir = folder / TRUTH_DIR
    truth_dir.mkdir()
    np.save(truth_dir / STAMPS_FILE, stamps)
    (truth_dir / TRUTH_FILE).write_text(json.dumps(truth, indent=1) + "\n", encoding="utf-8")


def _add_stamp(frame: np.ndarray, stamp: np.ndarray, left: int, top: int) -> None:
    """Add ``stamp`` to ``frame`` with its corner at ``(left, top)``, clipped to the frame."""
    h, w = frame.shape
    s = stamp.shape[0]
    y0, x0 = max(top, 0), max(left, 0)
    y1, x1 = min(top + s, h), min(left + s, w)
    if y1 > y0 and x1 > x0:
        frame[y0:y1, x0:x1] += stamp[y0 - top:y1 - top, x0 - left:x1 - left]


def cutout_scan(scan_dir: str | os.PathLike, out_dir: str | os.PathLike, size: int = 63,
                overwrite: bool = False) -> Path:
    """Write a compact-PSF scan as ``size × size`` cut-outs centred on each source's nearest pixel
    (clamped to the frame), with the truth in the crops' frames (``position_px`` relative to the
    crop, ``shift_px`` the centring residual, ``crop_corner_px``).

    Parameters
    ----------
    scan_dir : path-like
        A scan of :func:`simulate_compact_scan`.
    out_dir : path-like
        Destination folder (written atomically).
    size : int
        Crop side, px (odd: the source at the middle pixel).
    overwrite : bool
        Replace an existing folder.
    """
    truth = read_compact_truth(scan_dir)
    h, w = truth.frame_shape
    if not 3 <= size <= min(h, w):
        raise ConfigurationError(f"cut-out size must be in [3, {min(h, w)}], got {size}")
    grid = read_grid(scan_dir, check_pixels=False)
    info = json.loads(json.dumps(truth.info))          # a deep copy to edit
    header = {"bit_depth": grid.bit_depth, "black_level": grid.black_level,
              "simulation": {**grid.metadata.get("simulation", {}), "cutout": size}}
    suffix = Path(grid.positions[0].file).suffix
    corners = []
    with GridWriter(out_dir, None, suffix=suffix, overwrite=overwrite, **header) as writer:
        for p, pos in enumerate(grid.positions):
            x, y = truth.position_px[p]
            left = int(np.clip(round(x) - size // 2, 0, w - size))
            top = int(np.clip(round(y) - size // 2, 0, h - size))
            corners.append((left, top))
            raw = grid.load(0, p).astype(grid.dtype)
            writer.add_scan(p, raw[:, top:top + size, left:left + size],
                            field_deg=pos.field_deg)
        ref = truth.position_px[0] - np.array(corners[0])
        for p, record in enumerate(info["positions"]):
            local = truth.position_px[p] - np.array(corners[p])
            record["position_px"] = [float(v) for v in local]
            record["shift_px"] = [float(v) for v in local - ref]
            record["crop_corner_px"] = list(corners[p])
            record["stamp_corner_px"] = [record["stamp_corner_px"][0] - corners[p][0],
                                         record["stamp_corner_px"][1] - corners[p][1]]
        info["frame_shape"] = [size, size]
        info["crop"] = {"size": size, "source_frame_shape": [h, w],
                        "meaning": "position_px relative to each crop; shift_px relative to "
                                   "the reference crop's source (the centring residual)"}
        _write_truth(writer.folder, truth.stamps, info)
    return Path(out_dir)


def read_compact_truth(scan_dir: str | os.PathLike) -> CompactTruth:
    """Load the ground truth of a scan of :func:`simulate_compact_scan` or :func:`cutout_scan`.

    Raises
    ------
    InvalidInputError
        No ``ground_truth/truth.json`` of the compact bench.
    """
    folder = Path(scan_dir) / TRUTH_DIR
    if not (folder / TRUTH_FILE).is_file():
        raise InvalidInputError(f"{scan_dir}: no {TRUTH_DIR}/{TRUTH_FILE} (not a simulated "
                                "scan)")
    info = read_json_file(folder / TRUTH_FILE)
    if "stamp_size" not in info:
        raise InvalidInputError(f"{scan_dir}: {TRUTH_DIR}/{TRUTH_FILE} is not a compact-PSF "
                                "bench truth")
    records = info["positions"]

    def column(key: str) -> np.ndarray:
        return np.array([r[key] for r in records], dtype=np.float64)

    return CompactTruth(field_deg=column("field_deg"), position_px=column("position_px"),
                        shift_px=column("shift_px"), flux_e=column("flux_e"),
                        fwhm_px=column("fwhm_px"), axis_ratio=column("axis_ratio"),
                        stamps=np.load(folder / STAMPS_FILE), info=info,
                        camera=CompactCamera.from_dict(info["camera"]))
