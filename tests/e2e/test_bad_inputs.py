"""Malformed inputs through the real command lines: one line, the culprit named, exit 2.

Table-driven: every row of ``CASES`` builds its malformed input in its own folder from small
shared fixtures (a simulated 3 × 3 grid, tiny pairs and kernel file, tiny checkpoints), runs
``psfkit`` or ``ekdun`` in a subprocess and asserts that

- the exit status is 2,
- stderr is exactly one non-empty line, which names the offending file or flag,
- no traceback appears anywhere,
- nothing new appeared in the case's folder (where its outputs would go).

Adding a row: ``Case(id, cli, build, names)`` where ``build(work, fx)`` writes what it needs
under ``work`` and returns the argument list; the builders below (``grid_case``,
``manifest_case``, ``kernel_case``, ``pairs_case``, ``checkpoint_case``...) cover the usual
shapes. Classes (issue 12): 1 non-finite values, 2 tracebacks, 3 resource exhaustion,
4 a bad second output, 5 an existing output without ``--overwrite``, 7 invalid values and
misleading messages (6, leftovers after a kill, is ``test_output_policy.py``'s kill test).
Classes of issue 21 (each fixed at one root): 8 sizes declared by headers (bombs: tiny or
sparse files that declare gigabytes), 9 numeric flags outside their range (one table,
``psfkit.io.flag_ranges.FLAGS``), 10 library warnings and logging, 11 control characters in
names, 12 non-finite or empty results, 13 paths outside their folder, 14 a run folder holding
foreign files. Class 15 (issue 43): empty paths, frames too small to hold a PSF, and messages
that blamed the wrong thing (a flag or input file named instead of the output it spoiled).

A case with ``bomb=True`` also runs under :data:`PEAK_WRAPPER`, a fresh Python process that
reports the peak resident memory of the command (its only child), which must stay under
:data:`BOMB_PEAK_BYTES`.
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import subprocess
import sys
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parents[2]
DEEP = "[" * 200_000 + "]" * 200_000
SMALL_EKDUN = {"iterations": 2, "prior": {"widths": [4, 8]}}
SMALL_LE_ADMM = {"iterations": 2, "denoiser": {"widths": [4, 8]}}


@dataclass(frozen=True)
class Fixtures:
    grid: Path              # simulated 3 × 3 uint16 RGB grid with dark frame (read-only)
    float_grid: Path        # the same grid stored as float32 TIFFs (read-only)
    pairs: Path             # 8 tiny pairs (16 × 16 × 3 float32 .npy)
    kernels: Path           # their 3-kernel model
    checkpoint: Path        # a 1-epoch EK-DUN checkpoint of the tiny pairs
    le_admm: Path           # a 1-epoch Le-ADMM-U checkpoint


@dataclass(frozen=True)
class Case:
    id: str
    cli: str                                            # "psfkit" or "ekdun"
    build: Callable[[Path, Fixtures], list[str]]        # makes the input, returns the argv
    names: str                                          # the error line must contain this
    cls: int = 0                                        # class of issue 12 or 21
    bomb: bool = False                                  # also: peak memory < BOMB_PEAK_BYTES
    absent: str = ""                                    # the error line must not contain this


# --------------------------------------------------------------------------- builders


def _copy_grid(src: Path, work: Path) -> Path:
    dst = work / "grid"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("ground_truth"))
    return dst


def _edit_manifest(grid: Path, edit: Callable[[dict], Any]) -> None:
    path = grid / "manifest.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc, indent=1))


def grid_case(*extra: str, command: str = "info", float_grid: bool = False,
              prepare: Callable[[Path], Any] | None = None
              ) -> Callable[[Path, Fixtures], list[str]]:
    """``psfkit COMMAND GRID EXTRA...`` on a copy of the grid, optionally modified."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        grid = _copy_grid(fx.float_grid if float_grid else fx.grid, work)
        if prepare is not None:
            prepare(grid)
        out = [f"--out={work / 'out.json'}"] if command in ("register", "mae") else []
        quiet = ["--quiet"] if command in ("info", "register", "mae", "fit-eigen",
                                           "report") else []
        return [command, str(grid), *quiet, *out,
                *(a.replace("{work}", str(work)) for a in extra)]
    return build


def _touch(relative: str) -> Callable[[Path], Any]:
    """``prepare`` for grid cases: a file at ``work/relative`` (``work`` = the grid's parent)."""
    def prepare(grid: Path) -> None:
        path = grid.parent / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("already here")
    return prepare


def manifest_case(edit: Callable[[dict], Any], command: str = "info"
                  ) -> Callable[[Path, Fixtures], list[str]]:
    return grid_case(command=command, prepare=lambda g: _edit_manifest(g, edit))


def manifest_text_case(text: Callable[[str], str]) -> Callable[[Path, Fixtures], list[str]]:
    def prepare(grid: Path) -> None:
        path = grid / "manifest.json"
        path.write_text(text(path.read_text()))
    return grid_case(prepare=prepare)


def position_edit(key: str, value: Any, index: int = 0) -> Callable[[dict], Any]:
    def edit(doc: dict) -> None:
        doc["positions"][index][key] = value
    return edit


def header_edit(key: str, value: Any) -> Callable[[dict], Any]:
    def edit(doc: dict) -> None:
        doc[key] = value
    return edit


def _csv_manifest(grid: Path, extra_cell: bool = False, bad_row: bool = False) -> None:
    doc = json.loads((grid / "manifest.json").read_text())
    lines = ["file,row,col,role"]
    for i, p in enumerate(doc["positions"]):
        row = "abc" if bad_row and i == 1 else p["row"]
        lines.append(f"{p['file']},{row},{p['col']},psf" + (",7" if extra_cell and i == 2
                                                               else ""))
    lines.append(f"{doc['dark_frame']},,,dark")
    (grid / "manifest.json").unlink()
    (grid / "manifest.csv").write_text("\n".join(lines) + "\n")


def _write_tiff(path: Path, hwc: np.ndarray) -> None:
    import tifffile

    tifffile.imwrite(path, hwc, photometric="rgb" if hwc.ndim == 3 else "minisblack")


def _poison_tiff(name: str, value: float = np.nan) -> Callable[[Path], Any]:
    """Put one non-finite pixel into a float32 TIFF of the grid."""
    def prepare(grid: Path) -> None:
        import tifffile

        image = tifffile.imread(grid / name)
        image[5, 7, 1] = value
        _write_tiff(grid / name, image)
    return prepare


def _replace_image(name: str, array: np.ndarray | None = None, raw: bytes | None = None
                   ) -> Callable[[Path], Any]:
    def prepare(grid: Path) -> None:
        if raw is not None:
            (grid / name).write_bytes(raw)
        else:
            _write_tiff(grid / name, array)
    return prepare


def _huge_npy_header(grid: Path) -> None:
    """A 20-byte-edit image: an .npy whose header declares 100000 × 100000 pixels."""
    path = grid / "psf_r00_c00.npy"
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(
            fh, {"descr": "<u2", "fortran_order": False, "shape": (100_000, 100_000)})
        fh.write(b"\0" * 64)
    (grid / "psf_r00_c00.tiff").unlink()
    _edit_manifest(grid, position_edit("file", "psf_r00_c00.npy"))


# kernel files -------------------------------------------------------------------------


def _rewrite_kernels(src: Path, dst: Path, meta_text: Callable[[str], str] | None = None,
                     kernels: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
    with np.load(src, allow_pickle=False) as data:
        k, text = np.array(data["kernels"]), str(data["metadata"])
    if kernels is not None:
        k = kernels(k)
    if meta_text is not None:
        text = meta_text(text)
    with open(dst, "wb") as fh:
        np.savez(fh, kernels=k, metadata=np.array(text))


def meta_edit(key: str, value: Any, raw: str | None = None) -> Callable[[str], str]:
    """Set a metadata field; ``raw`` is spliced verbatim (NaN literals, nesting...)."""
    def edit(text: str) -> str:
        doc = json.loads(text)
        doc[key] = "@@RAW@@" if raw is not None else value
        out = json.dumps(doc)
        return out.replace('"@@RAW@@"', raw) if raw is not None else out
    return edit


def kernel_case(meta_text: Callable[[str], str] | None = None,
                kernels: Callable[[np.ndarray], np.ndarray] | None = None,
                raw: bytes | None = None) -> Callable[[Path, Fixtures], list[str]]:
    """``psfkit eval-model K.npz PAIRS --out`` with a modified kernel file."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        target = work / "k.npz"
        if raw is not None:
            target.write_bytes(raw)
        else:
            _rewrite_kernels(fx.kernels, target, meta_text, kernels)
        return ["eval-model", str(target), str(fx.pairs), "--out", str(work / "errors.json")]
    return build


# pairs --------------------------------------------------------------------------------


def pairs_case(prepare: Callable[[Path], Any] | None = None, command: str = "eval-model",
               *extra: str) -> Callable[[Path, Fixtures], list[str]]:
    """``psfkit eval-model K PAIRS`` (or ``fit-pairs``) on a modified copy of the pairs."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        pairs = work / "pairs"
        shutil.copytree(fx.pairs, pairs)
        if prepare is not None:
            prepare(pairs)
        more = [a.replace("{work}", str(work)) for a in extra]
        if command == "fit-pairs":
            return ["fit-pairs", str(pairs), "--out", str(work / "model.npz"), "--quiet",
                    *more]
        return ["eval-model", str(fx.kernels), str(pairs), "--out", str(work / "e.json"),
                *more]
    return build


def pairs_json(text: str) -> Callable[[Path], Any]:
    return lambda pairs: (pairs / "pairs.json").write_text(text)


def _edit_scene(name: str, edit: Callable[[np.ndarray], np.ndarray],
                folder: str = "scene") -> Callable[[Path], Any]:
    def prepare(pairs: Path) -> None:
        path = pairs / folder / name
        np.save(path, edit(np.load(path)))
    return prepare


def _nan_pixel(a: np.ndarray) -> np.ndarray:
    a = a.copy()
    a[3, 4, 0] = np.nan
    return a


# ekdun ----------------------------------------------------------------------------------


def ekdun_case(*args: str) -> Callable[[Path, Fixtures], list[str]]:
    """``ekdun ARGS`` with ``{pairs}``, ``{kernels}``, ``{psf}``, ``{meas}``, ``{work}``,
    ``{ckpt}`` filled in (``{psf}``/``{meas}`` are written into the case folder)."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        names = {"pairs": fx.pairs, "kernels": fx.kernels, "work": work,
                 "ckpt": fx.checkpoint, "psf": work / "psf.npy", "meas": work / "meas.npy"}
        if any("{psf}" in a or "{meas}" in a for a in args):
            _tiny_admm_inputs(work)
        return [a.format(**names) for a in args]
    return build


def _tiny_admm_inputs(work: Path, nan_in: str | None = None) -> None:
    rng = np.random.default_rng(0)
    psf = np.zeros((32, 32), np.float32)
    psf[14:18, 12:20] = 1.0
    meas = rng.random((32, 32)).astype(np.float32)
    if nan_in == "psf":
        psf[16, 16] = np.nan
    if nan_in == "meas":
        meas[3, 3] = np.inf
    np.save(work / "psf.npy", psf)
    np.save(work / "meas.npy", meas)


def admm_nan_case(where: str, command: str = "admm") -> Callable[[Path, Fixtures], list[str]]:
    """``ekdun admm PSF MEAS`` (or ``ekdun train PAIRS --psf PSF``) with one NaN/Inf."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        _tiny_admm_inputs(work, nan_in=where)
        if command == "train":
            psf = np.zeros((16, 16, 3), np.float32)
            psf[8, 8] = [1.0, np.nan, 1.0]
            np.save(work / "psf.npy", psf)
            return ["train", str(fx.pairs), str(work / "run"), "--psf", str(work / "psf.npy"),
                    "--quiet", "--epochs", "1"]
        return ["admm", str(work / "psf.npy"), str(work / "meas.npy"), "--out",
                str(work / "x.npy"), "--iterations", "2"]
    return build


def bench_config_case(text: str) -> Callable[[Path, Fixtures], list[str]]:
    """``psfkit simulate-grid --bench-config bench.json`` with a malformed JSON file."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        (work / "bench.json").write_text(text)
        return ["simulate-grid", "--out", str(work / "g"), "--bench-config",
                str(work / "bench.json"), "--quiet"]
    return build


def checkpoint_case(edit: Callable[[dict], Any] | None, command: str = "reconstruct",
                    raw: bytes | None = None, source: str = "checkpoint"
                    ) -> Callable[[Path, Fixtures], list[str]]:
    """``ekdun reconstruct|eval|export-kernels`` with a modified copy of a checkpoint."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        import torch

        target = work / "checkpoint.pt"
        if raw is not None:
            target.write_bytes(raw)
        else:
            doc = torch.load(getattr(fx, source), weights_only=True)
            if edit is not None:
                edit(doc)
            torch.save(doc, target)
        if command == "eval":
            return ["eval", str(target), "--data", str(fx.pairs), "--out", str(work / "tables")]
        if command == "export-kernels":
            return ["export-kernels", str(target), "--out", str(work / "k.npz")]
        meas = work / "m.npy"
        np.save(meas, np.load(fx.pairs / "measurement" / "im0.npy"))
        return ["reconstruct", str(target), str(meas), "--out", str(work / "recon")]
    return build


def _nan_weight(doc: dict) -> None:
    name = next(k for k, v in doc["model"].items() if v.is_floating_point() and v.numel() > 1)
    doc["model"][name].view(-1)[0] = float("nan")


def _ckpt_meta(edit: Callable[[dict], Any] | None = None, text: str | None = None
               ) -> Callable[[dict], Any]:
    def apply(doc: dict) -> None:
        if text is not None:
            doc["metadata"] = text
        else:
            meta = json.loads(doc["metadata"])
            edit(meta)
            doc["metadata"] = json.dumps(meta)
    return apply


# bombs (issue 21): tiny or sparse files whose headers declare gigabytes -------------------


def _sparse_npy(path: Path, shape: tuple[int, ...], descr: str = "<f4") -> None:
    """A valid ``.npy`` of ``shape`` whose data is a hole: kilobytes on disk, gigabytes read."""
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(
            fh, {"descr": descr, "fortran_order": False, "shape": shape})
        fh.truncate(fh.tell() + int(np.prod(shape)) * np.dtype(descr).itemsize)


def _zlib_zeros(n: int) -> bytes:
    """A zlib stream of ``n`` zero bytes (``n`` >= 2 MiB), built in milliseconds: after a full
    flush the compressor forgets its history, so every further MiB compresses alike."""
    mib = 1 << 20
    c = zlib.compressobj(9)
    head = c.compress(bytes(mib)) + c.flush(zlib.Z_FULL_FLUSH)
    block = c.compress(bytes(mib)) + c.flush(zlib.Z_FULL_FLUSH)
    full, rest = divmod(n - mib, mib)
    tail = c.compress(bytes(rest)) + c.flush()
    adler = ((n % 65521) << 16) | 1             # Adler-32 of n zero bytes
    return head + block * full + tail[:-4] + struct.pack(">I", adler)


def _png(path: Path, side: int, idat: bytes) -> None:
    """An 8-bit RGB PNG of ``side`` x ``side`` pixels with the given compressed data."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat)
                     + chunk(b"IEND", b""))


def _png_bomb(path: Path, side: int = 30_000) -> None:
    """An 8-bit RGB PNG of ``side`` x ``side`` zeros (2.7 GB decoded) in about 3 MB."""
    _png(path, side, _zlib_zeros(side * (3 * side + 1)))


def _tiff_page_stack(path: Path) -> None:
    """40 pages of 4096 x 4096 uint16 (1.3 GB) in a sparse file: each page passes a 2-D size
    check, the stack does not."""
    import tifffile

    tifffile.imwrite(path, shape=(40, 4096, 4096), dtype="uint16", photometric="minisblack",
                     metadata=None)


def _kernels_zip_bomb(path: Path) -> None:
    """A kernel file whose ``kernels`` member inflates to 1.2 GB (6 x 3 x 4096 x 4096 float32
    zeros) from about 5 MB; its metadata is valid."""
    meta = json.dumps({"format": "ekdun-kernels", "version": 1, "basis": "si",
                       "channels": ["R", "G", "B"], "sensor_shape": [4096, 4096]})
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        with archive.open("kernels.npy", "w", force_zip64=True) as member:
            np.lib.format.write_array_header_1_0(
                member, {"descr": "<f4", "fortran_order": False, "shape": (6, 3, 4096, 4096)})
            block = bytes(1 << 24)
            for _ in range(6 * 3 * 4096 * 4096 * 4 // len(block)):
                member.write(block)
        with archive.open("metadata.npy", "w") as member:
            np.lib.format.write_array(member, np.array(meta))


def _sparse_json(path: Path, size: int = 2**30) -> None:
    with open(path, "wb") as fh:
        fh.write(b'{"a": "')
        fh.truncate(size)


def bomb_pairs_case(make: Callable[[Path], Any], name: str
                    ) -> Callable[[Path, Fixtures], list[str]]:
    """``eval-model`` on pairs whose scene ``name`` (replacing im0) is a bomb."""
    def prepare(pairs: Path) -> None:
        (pairs / "scene" / "im0.npy").unlink()
        make(pairs / "scene" / name)
    return pairs_case(prepare)


def admm_kernels_case(kernels: Callable[[np.ndarray], np.ndarray] | None = None,
                      raw: Callable[[Path], Any] | None = None
                      ) -> Callable[[Path, Fixtures], list[str]]:
    """``ekdun reconstruct K.npz MEAS --out X`` (classical, formerly ``ekdun admm --kernels``)
    with a modified kernel file."""
    def build(work: Path, fx: Fixtures) -> list[str]:
        target = work / "k.npz"
        if raw is not None:
            raw(target)
        else:
            _rewrite_kernels(fx.kernels, target, kernels=kernels)
        meas = work / "m.npy"
        np.save(meas, np.load(fx.pairs / "measurement" / "im0.npy"))
        return ["reconstruct", str(target), str(meas), "--out", str(work / "outdir"),
                "--iterations", "2", "--quiet"]
    return build


def _save_array(relative: str, array: np.ndarray) -> Callable[[Path], Any]:
    """``prepare`` for pairs cases: an array at ``pairs/../relative``."""
    return lambda pairs: np.save(pairs.parent / relative, array)


def _ckpt_sensor(size: int) -> Callable[[dict], Any]:
    def edit(meta: dict) -> None:
        meta["sensor_shape"] = [size, size]
        meta["kernel_metadata"]["sensor_shape"] = [size, size]
    return edit


def _newline_named_scene(pairs: Path) -> None:
    """A scene whose file name holds a newline (and a NaN, so that it is refused by name)."""
    scene = _nan_pixel(np.load(pairs / "scene" / "im2.npy"))
    (pairs / "scene" / "im2.npy").unlink()
    (pairs / "measurement" / "im2.npy").rename(pairs / "measurement" / "im\n2.npy")
    np.save(pairs / "scene" / "im\n2.npy", scene)


TRAIN = ("train", "{pairs}", "{work}/run", "--kernels", "{kernels}", "--quiet", "--epochs", "1")


# issue 43 ------------------------------------------------------------------------------


def _crop_frames(side: int) -> Callable[[Path], Any]:
    """``prepare`` for grid cases: every frame (PSFs and dark) cut to ``side`` × ``side`` px
    around the centre PSF's peak."""
    def prepare(grid: Path) -> None:
        import tifffile

        peak = np.unravel_index(np.argmax(tifffile.imread(grid / "psf_r01_c01.tiff")[..., 1]),
                                (135, 180))
        top, left = (max(0, min(int(p) - side // 2, n - side)) for p, n in zip(peak, (135, 180),
                                                                            strict=True))
        for f in grid.glob("*.tiff"):
            _write_tiff(f, tifffile.imread(f)[top:top + side, left:left + side])
    return prepare


def _one_channel_kernels(work: Path, fx: Fixtures) -> list[str]:
    """``eval-model`` of a 1-channel (mono) kernel file on the RGB pairs."""
    from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels

    rgb = load_kernels(fx.kernels)
    save_kernels(work / "mono.npz", KernelModel(kernels=rgb.kernels[:, :1], basis=rgb.basis,
                                                channels=("L",), sensor_shape=rgb.sensor_shape))
    return ["eval-model", str(work / "mono.npz"), str(fx.pairs), "--out", str(work / "e.json")]


def _huge_kernel(k: np.ndarray) -> np.ndarray:
    """Finite values whose forward model overflows float32 (the sweep's "huge finite")."""
    return (k * np.float32(1e30)).astype(np.float32)


# --------------------------------------------------------------------------- the table

CASES: list[Case] = [
    # ---- class 1: non-finite values --------------------------------------------------
    Case("black-level-overflow", "psfkit",
         manifest_text_case(lambda t: t.replace('"black_level": 1024.0', '"black_level": 1e400')),
         "manifest.json", 1),
    Case("black-level-infinity", "psfkit", manifest_case(header_edit("black_level", np.inf)),
         "manifest.json", 1),
    Case("black-level-nan-literal", "psfkit",
         manifest_text_case(lambda t: t.replace('"black_level": 1024.0', '"black_level": NaN')),
         "manifest.json", 1),
    Case("black-level-huge-negative", "psfkit",
         manifest_case(header_edit("black_level", -1e30)), "black_level", 1),
    Case("field-deg-overflow", "psfkit",
         manifest_text_case(lambda t: t.replace("-9.645550545", "-1e999", 1)), "1e999", 1),
    # --strict: all or nothing (without it the position is flagged and excluded, issue 26)
    Case("psf-nan-pixel", "psfkit", grid_case("--strict", float_grid=True,
                                              prepare=_poison_tiff("psf_r00_c02.tiff")),
         "psf_r00_c02.tiff", 1),
    Case("psf-nan-pixel-register-strict", "psfkit",
         grid_case("--strict", command="register", float_grid=True,
                   prepare=_poison_tiff("psf_r00_c02.tiff")), "psf_r00_c02.tiff", 1),
    Case("dark-nan-info", "psfkit", grid_case(float_grid=True, prepare=_poison_tiff("dark.tiff")),
         "dark.tiff", 1),
    Case("dark-nan-register", "psfkit",
         grid_case(command="register", float_grid=True, prepare=_poison_tiff("dark.tiff")),
         "dark.tiff", 1),
    Case("dark-inf-mae", "psfkit",
         grid_case(command="mae", float_grid=True, prepare=_poison_tiff("dark.tiff", np.inf)),
         "dark.tiff", 1),
    Case("saturation-level-nan", "psfkit", grid_case("--saturation-level", "nan",
                                                     command="register"),
         "--saturation-level", 1),
    Case("hot-pixel-sigma-nan", "psfkit", grid_case("--hot-pixel-sigma", "nan",
                                                    command="register"),
         "--hot-pixel-sigma", 1),
    Case("mae-smoothing-nan", "psfkit", grid_case("--mae-smoothing", "nan", command="mae"),
         "--mae-smoothing", 1),
    Case("kernel-optical-center-nan", "psfkit",
         kernel_case(meta_edit("optical_center", None, raw="[NaN, 8.0]")), "k.npz", 1),
    Case("kernel-optical-center-inf", "psfkit",
         kernel_case(meta_edit("optical_center", None, raw="[1e400, 8.0]")), "1e400", 1),
    Case("kernel-optical-center-far", "psfkit",
         kernel_case(meta_edit("optical_center", [1e30, 8.0])), "optical_center", 1),
    Case("kernel-nan-weight", "psfkit",
         kernel_case(kernels=lambda k: np.where(np.arange(k.size).reshape(k.shape) == 5,
                                                np.nan, k).astype(np.float32)),
         "k.npz", 1),
    Case("pairs-scene-nan", "psfkit", pairs_case(_edit_scene("im2.npy", _nan_pixel)),
         "im2.npy", 1),
    Case("pairs-measurement-nan", "psfkit",
         pairs_case(_edit_scene("im5.npy", _nan_pixel, "measurement")), "im5.npy", 1),
    Case("fit-pairs-tikhonov-nan", "psfkit", pairs_case(None, "fit-pairs", "--tikhonov", "nan"),
         "--tikhonov", 1),
    Case("admm-psf-nan", "ekdun", admm_nan_case("psf"), "psf.npy", 1),
    Case("admm-measurement-inf", "ekdun", admm_nan_case("meas"), "meas.npy", 1),
    Case("admm-tau-nan", "ekdun", ekdun_case("admm", "{psf}", "{meas}", "--out", "{work}/x.npy",
                                             "--tau", "nan"), "--tau", 1),
    Case("train-lr-nan", "ekdun", ekdun_case("train", "{pairs}", "{work}/run", "--kernels",
                                             "{kernels}", "--lr", "nan"), "--lr", 1),
    Case("make-dataset-photons-nan", "ekdun", ekdun_case("make-dataset", "{work}/ds",
                                                         "--photons", "nan"), "--photons", 1),
    Case("train-psf-nan", "ekdun", admm_nan_case("psf", command="train"), "psf.npy", 1),
    Case("checkpoint-nan-weight-reconstruct", "ekdun", checkpoint_case(_nan_weight),
         "checkpoint.pt", 1),
    Case("checkpoint-nan-weight-eval", "ekdun", checkpoint_case(_nan_weight, "eval"),
         "checkpoint.pt", 1),

    # ---- class 2: tracebacks ---------------------------------------------------------
    Case("manifest-deep-nesting", "psfkit", manifest_text_case(lambda t: DEEP), "manifest.json",
         2),
    Case("manifest-deep-field", "psfkit",
         manifest_text_case(lambda t: t.replace('"bit_depth": 12', f'"extra": {DEEP}', 1)),
         "manifest.json", 2),
    Case("manifest-csv-extra-cell", "psfkit",
         grid_case(prepare=lambda g: _csv_manifest(g, extra_cell=True)), "manifest.csv", 2),
    Case("manifest-csv-row-text", "psfkit",
         grid_case(prepare=lambda g: _csv_manifest(g, bad_row=True)), "row", 2),
    Case("manifest-not-utf8", "psfkit",
         grid_case(prepare=lambda g: (g / "manifest.json").write_bytes(b"\xff\xfe{\x00")),
         "manifest.json", 2),
    Case("manifest-empty", "psfkit",
         grid_case(prepare=lambda g: (g / "manifest.json").write_bytes(b"")), "manifest.json",
         2),
    Case("manifest-top-level-list", "psfkit", manifest_text_case(lambda t: "[1, 2]"),
         "manifest.json", 2),
    Case("manifest-grid-shape-text", "psfkit", manifest_case(header_edit("grid_shape", "3x3")),
         "grid_shape", 2),
    Case("manifest-exposure-text", "psfkit",
         manifest_case(position_edit("exposure_s", "fast")), "exposure_s", 2),
    Case("manifest-monitor-text", "psfkit", manifest_case(position_edit("monitor_px", "abc")),
         "monitor_px", 2),
    Case("manifest-center-bool", "psfkit", manifest_case(header_edit("center", [True, 0])),
         "center", 2),
    Case("manifest-file-path", "psfkit",
         manifest_case(position_edit("file", "../psf_r00_c00.tiff")), "psf_r00_c00.tiff", 2),
    Case("image-zero-bytes", "psfkit", grid_case(prepare=_replace_image("psf_r01_c01.tiff",
                                                                        raw=b"")),
         "psf_r01_c01.tiff", 2),
    Case("image-garbage", "psfkit",
         grid_case(prepare=_replace_image("psf_r01_c00.tiff", raw=b"II*\x00garbage" * 10)),
         "psf_r01_c00.tiff", 2),
    Case("image-four-channels", "psfkit", grid_case(prepare=_replace_image(
        "psf_r02_c02.tiff", np.ones((135, 180, 4), np.uint16))), "psf_r02_c02.tiff", 2),
    Case("kernel-zero-byte-npz", "psfkit", kernel_case(raw=b""), "k.npz", 2),
    Case("kernel-not-a-zip", "psfkit", kernel_case(raw=b"PK\x03\x04 truncated"), "k.npz", 2),
    Case("kernel-deep-metadata", "psfkit", kernel_case(lambda t: DEEP), "k.npz", 2),
    Case("kernel-sensor-shape-text", "psfkit",
         kernel_case(meta_edit("sensor_shape", "16x16")), "sensor_shape", 2),
    Case("kernel-scene-padding-text", "psfkit",
         kernel_case(meta_edit("scene_padding", "two")), "scene_padding", 2),
    Case("kernel-basis-number", "psfkit", kernel_case(meta_edit("basis", 5)), "basis", 2),
    Case("kernel-optical-center-text", "psfkit",
         kernel_case(meta_edit("optical_center", ["a", "b"])), "optical_center", 2),
    Case("kernel-provenance-downsample-text", "psfkit",
         kernel_case(meta_edit("provenance", {"downsample": "x"})), "downsample", 2),
    Case("pairs-json-scene-dir-number", "psfkit", pairs_case(pairs_json('{"scene_dir": 5}')),
         "scene_dir", 2),
    # the data contract (issue 21): white levels and recorded read options
    Case("pairs-json-white-level-huge", "psfkit",
         pairs_case(pairs_json('{"white_level": 1e308}')), "white_level", 7),
    Case("pairs-json-white-level-text", "psfkit",
         pairs_case(pairs_json('{"white_level": "255"}')), "white_level", 7),
    Case("kernel-read-options-downsample-zero", "psfkit",
         kernel_case(meta_edit("read_options", {"downsample": 0})), "read_options", 2),
    Case("kernel-read-options-order", "psfkit",
         kernel_case(meta_edit("read_options", {"channel_order": "GRB"})), "read_options", 2),
    Case("kernel-origin-other", "psfkit",
         kernel_case(meta_edit("kernel_origin", "top-left (0, 0)")), "kernel_origin", 2),
    Case("pairs-json-deep", "psfkit", pairs_case(pairs_json(DEEP)), "pairs.json", 2),
    Case("pairs-json-list", "psfkit", pairs_case(pairs_json("[]")), "pairs.json", 2),
    Case("pairs-zero-byte-image", "psfkit",
         pairs_case(lambda p: (p / "scene" / "im3.npy").write_bytes(b"")), "im3.npy", 2),
    Case("mae-smoothing-text", "psfkit", grid_case("--mae-smoothing", "wide", command="mae"),
         "--mae-smoothing", 2),
    Case("bench-config-deep", "psfkit", bench_config_case(DEEP), "bench.json", 2),
    Case("bench-config-duplicate-key", "psfkit",
         bench_config_case('{"seed": 1, "seed": 2}'), "seed", 7),
    Case("train-lr-negative", "ekdun", ekdun_case("train", "{pairs}", "{work}/run", "--kernels",
                                                  "{kernels}", "--lr", "-1"), "--lr", 2),
    Case("checkpoint-zero-bytes", "ekdun", checkpoint_case(None, raw=b""), "checkpoint.pt", 2),
    Case("checkpoint-deep-metadata", "ekdun",
         checkpoint_case(_ckpt_meta(text=DEEP)), "checkpoint.pt", 2),

    # ---- class 3: resource exhaustion ------------------------------------------------
    Case("manifest-huge-row", "psfkit", manifest_case(position_edit("row", 100_000_000)),
         "row", 3),
    Case("manifest-huge-grid-shape", "psfkit",
         manifest_case(header_edit("grid_shape", [100_000, 100_000])), "grid_shape", 3),
    Case("manifest-huge-center", "psfkit", manifest_case(header_edit("center", [10**9, 1])),
         "center", 3),
    Case("image-huge-npy-header", "psfkit", grid_case(prepare=_huge_npy_header),
         "psf_r00_c00.npy", 3),
    Case("kernel-huge-scene-padding", "psfkit",
         kernel_case(meta_edit("scene_padding", 10**12)), "scene_padding", 3),
    Case("kernel-huge-sensor-shape", "psfkit",
         kernel_case(meta_edit("sensor_shape", [100_000, 100_000])), "sensor_shape", 3),
    Case("checkpoint-huge-iterations", "ekdun",
         checkpoint_case(_ckpt_meta(lambda m: m.setdefault("overrides", {}).update(
             iterations=10**9))), "checkpoint.pt", 3),
    Case("train-huge-iterations", "ekdun", ekdun_case("train", "{pairs}", "{work}/run",
                                                      "--kernels", "{kernels}", "--iterations",
                                                      "100000"), "--iterations", 3),
    Case("make-dataset-huge-sensor", "ekdun", ekdun_case("make-dataset", "{work}/ds", "--sensor",
                                                         "100000", "100000"), "--sensor", 3),

    # ---- class 7: invalid values, misleading messages --------------------------------
    Case("register-workers-negative", "psfkit", grid_case("--threads", "-1", command="register"),
         "--threads", 7),
    Case("register-saturation-negative", "psfkit",
         grid_case("--saturation-level", "-5", command="register"), "--saturation-level", 7),
    Case("register-upsample-zero", "psfkit", grid_case("--upsample", "0", command="register"),
         "--upsample", 7),
    Case("manifest-bit-depth-true", "psfkit", manifest_case(header_edit("bit_depth", True)),
         "bit_depth", 7),
    Case("manifest-version-true", "psfkit", manifest_case(header_edit("version", True)),
         "version", 7),
    Case("manifest-duplicate-key", "psfkit",
         manifest_text_case(lambda t: t.replace('"bit_depth": 12', '"bit_depth": 12, '
                                                '"bit_depth": 16', 1)),
         "bit_depth", 7),
    Case("manifest-unknown-position-key", "psfkit",
         manifest_case(position_edit("exposure", 0.01)), "exposure", 7),
    Case("kernel-version-true", "psfkit", kernel_case(meta_edit("version", True)), "k.npz", 7),
    Case("kernel-scene-padding-true", "psfkit", kernel_case(meta_edit("scene_padding", True)),
         "scene_padding", 7),
    Case("kernel-duplicate-key", "psfkit",
         kernel_case(lambda t: t.replace('"basis": "paper"', '"basis": "paper", "basis": "si"')),
         "basis", 7),
    Case("pairs-json-duplicate-key", "psfkit",
         pairs_case(pairs_json('{"flip": "ud", "flip": "none"}')), "flip", 7),
    Case("pairs-json-unknown-key", "psfkit", pairs_case(pairs_json('{"scenes": "scene"}')),
         "scenes", 7),
    Case("pairs-mixed-dtypes", "psfkit",
         pairs_case(_edit_scene("im4.npy", lambda a: (a * 1000).astype(np.uint16))), "im4.npy",
         7),
    Case("pairs-all-zero-scene", "psfkit",
         pairs_case(_edit_scene("im1.npy", np.zeros_like), "fit-pairs"), "im1.npy", 7),
    Case("eval-model-downsample-zero", "psfkit", pairs_case(None, "eval-model", "--downsample",
                                                            "0"), "--downsample", 7),
    Case("fit-pairs-iterations-zero", "psfkit", pairs_case(None, "fit-pairs", "--iterations",
                                                           "0"), "--iterations", 7),
    Case("admm-downsample-zero", "ekdun", ekdun_case("admm", "{psf}", "{meas}", "--out",
                                                     "{work}/x.npy", "--downsample", "0"),
         "--downsample", 7),
    Case("admm-downsample-huge", "ekdun", ekdun_case("admm", "{psf}", "{meas}", "--out",
                                                     "{work}/x.npy", "--downsample", "5000"),
         "--downsample", 7),
    Case("admm-iterations-zero", "ekdun", ekdun_case("admm", "{psf}", "{meas}", "--out",
                                                     "{work}/x.npy", "--iterations", "0"),
         "--iterations", 7),
    Case("train-epochs-zero", "ekdun", ekdun_case("train", "{pairs}", "{work}/run", "--kernels",
                                                  "{kernels}", "--epochs", "0"), "--epochs", 7),
    Case("train-batch-size-negative", "ekdun", ekdun_case("train", "{pairs}", "{work}/run",
                                                          "--kernels", "{kernels}",
                                                          "--batch-size", "-2"),
         "--batch-size", 7),
    Case("export-kernels-le-admm-u", "ekdun",
         checkpoint_case(None, "export-kernels", source="le_admm"), "checkpoint.pt", 7),
    # class 4: one bad output path fails the whole command before any work, nothing written
    Case("fit-eigen-figures-ok-out-under-a-file", "psfkit",
         grid_case("--figures", "{work}/figs", "--out", "{work}/afile/k.npz",
                   command="fit-eigen", prepare=_touch("afile")), "afile", 4),
    Case("fit-pairs-report-under-a-file", "psfkit",
         pairs_case(lambda pairs: (pairs.parent / "afile").write_text("x"), "fit-pairs",
                    "--report", "{work}/afile/r.json"), "afile", 4),
    Case("eval-model-out-under-a-file", "psfkit",
         pairs_case(lambda pairs: (pairs.parent / "e.json").mkdir(), "eval-model"),
         "e.json", 4),
    # class 5: an existing output is never replaced without --overwrite (files and folders)
    Case("register-out-exists", "psfkit",
         grid_case(command="register", prepare=_touch("out.json")), "out.json", 5),
    Case("fit-eigen-out-exists", "psfkit",
         grid_case("--out", "{work}/k.npz", command="fit-eigen", prepare=_touch("k.npz")),
         "k.npz", 5),
    Case("report-folder-exists", "psfkit",
         grid_case("--out", "{work}/rep", command="report", prepare=_touch("rep/index.html")),
         "rep", 5),
    Case("fit-pairs-out-exists", "psfkit",
         pairs_case(lambda pairs: (pairs.parent / "model.npz").write_text("x"), "fit-pairs"),
         "model.npz", 5),

    # ---- issue 21, class 8: sizes declared by headers, checked before any allocation ----
    Case("png-declares-30000-squared", "psfkit", bomb_pairs_case(_png_bomb, "im0.png"),
         "im0.png", 8, bomb=True),
    Case("tiff-page-stack", "psfkit", bomb_pairs_case(_tiff_page_stack, "im0.tiff"),
         "im0.tiff", 8, bomb=True),
    Case("npy-huge-third-axis", "psfkit",
         bomb_pairs_case(lambda p: _sparse_npy(p, (16, 16, 2_000_000)), "im0.npy"),
         "im0.npy", 8, bomb=True),
    Case("npz-kernels-zip-bomb", "ekdun", admm_kernels_case(raw=_kernels_zip_bomb),
         "kernels", 8, bomb=True),
    Case("manifest-json-sparse-1gb", "psfkit",
         grid_case(prepare=lambda g: _sparse_json(g / "manifest.json")), "manifest.json", 8,
         bomb=True),
    Case("pairs-json-sparse-1gb", "psfkit",
         pairs_case(lambda p: _sparse_json(p / "pairs.json")), "pairs.json", 8, bomb=True),
    Case("checkpoint-widths-4000", "ekdun",
         checkpoint_case(_ckpt_meta(lambda m: m["overrides"]["prior"].update(
             widths=[4, 4000]))), "widths", 8, bomb=True),
    Case("checkpoint-sensor-4096", "ekdun", checkpoint_case(_ckpt_meta(_ckpt_sensor(4096))),
         "checkpoint.pt", 8, bomb=True),
    Case("checkpoint-sensor-4096-export", "ekdun",
         checkpoint_case(_ckpt_meta(_ckpt_sensor(4096)), "export-kernels"), "sensor_shape", 8,
         bomb=True),

    # ---- class 9: every numeric flag has its range (one table); --device is checked ------
    Case("train-device-bogus", "ekdun", ekdun_case(*TRAIN, "--device", "bogus"), "--device", 9),
    Case("train-device-missing-gpu", "ekdun", ekdun_case(*TRAIN, "--device", "cuda:99"),
         "--device", 9),
    Case("eval-device-missing-gpu", "ekdun",
         lambda work, fx: [*checkpoint_case(None, "eval")(work, fx), "--device", "cuda:99"],
         "--device", 9),
    Case("reconstruct-device-bogus", "ekdun",
         ekdun_case("reconstruct", "{ckpt}", "{meas}", "--out", "{work}/r", "--device", "gpu"),
         "--device", 9),
    Case("train-downsample-zero", "ekdun", ekdun_case(*TRAIN, "--downsample", "0"),
         "--downsample", 9),
    Case("train-downsample-negative", "ekdun", ekdun_case(*TRAIN, "--downsample", "-2"),
         "--downsample", 9),
    Case("train-lr-1e308", "ekdun", ekdun_case(*TRAIN, "--lr", "1e308"), "--lr", 9),
    Case("train-threads-100000", "ekdun", ekdun_case(*TRAIN, "--threads", "100000"),
         "--threads", 9),
    Case("train-seed-2-70", "ekdun", ekdun_case(*TRAIN, "--seed", str(2**70)), "--seed", 9),
    Case("train-seed-negative", "ekdun", ekdun_case(*TRAIN, "--seed", "-1"), "--seed", 9),
    Case("train-iterations-above-max", "ekdun", ekdun_case(*TRAIN, "--iterations", "101"),
         "--iterations", 9),
    Case("mae-smoothing-1e308", "psfkit", grid_case("--mae-smoothing", "1e308", command="mae"),
         "--mae-smoothing", 9),
    Case("mae-smoothing-1e6", "psfkit", grid_case("--mae-smoothing", "1e6", command="mae"),
         "--mae-smoothing", 9),
    Case("simulate-gap-1e308", "psfkit",
         ekdun_case("simulate-grid", "--out", "{work}/g", "--gap-mm", "1e308"), "--gap-mm", 9),
    Case("simulate-diffusion-angle-90", "psfkit",
         ekdun_case("simulate-grid", "--out", "{work}/g", "--diffusion-angle", "90"),
         "--diffusion-angle", 9),
    Case("simulate-rows-65", "psfkit",
         ekdun_case("simulate-grid", "--out", "{work}/g", "--rows", "65", "--cols", "3"),
         "--rows", 9),
    Case("bench-config-diffusion-angle-90", "psfkit",
         bench_config_case('{"diffusion_angle_deg": 90}'), "--diffusion-angle", 9),
    Case("bench-config-gap-1000-grid-too-large", "psfkit",
         bench_config_case('{"gap_mm": 1000}'), "gap_mm", 9),
    Case("fit-pairs-iterations-above-max", "psfkit",
         pairs_case(None, "fit-pairs", "--iterations", "100000"), "--iterations", 9),
    Case("admm-iterations-above-max", "ekdun",
         ekdun_case("admm", "{psf}", "{meas}", "--out", "{work}/x.npy", "--iterations",
                    "100000"), "--iterations", 9),
    Case("admm-kernels-all-zero", "ekdun", admm_kernels_case(kernels=np.zeros_like), "k.npz",
         12),

    # ---- class 10: warnings and library logging become the one line (or nothing) -------
    Case("manifest-exposure-huge", "psfkit",
         manifest_case(position_edit("exposure_s", 1e300, index=2), command="mae"),
         "exposure_s", 10),
    Case("manifest-exposure-tiny", "psfkit",
         manifest_case(position_edit("exposure_s", 1e-300, index=2), command="mae"),
         "exposure_s", 10),
    Case("png-libpng-warning-then-error", "psfkit",
         bomb_pairs_case(lambda p: _png(p, 16, b"garbage!" * 4), "im0.png"),   # libpng error
         "im0.png", 10),

    # ---- class 11: names escaped: a newline in a file name does not split the line ------
    Case("pairs-newline-in-name", "psfkit", pairs_case(_newline_named_scene), "im\\n2.npy",
         11),
    Case("grid-newline-in-name", "psfkit",
         lambda work, fx: ["info", str(work / "no\nsuch grid")], "no\\nsuch grid", 11),

    # ---- class 12: results checked finite (and not empty) before they are committed ----
    Case("make-dataset-photons-1e-300", "ekdun",   # issue 43: the flag, not the output
         ekdun_case("make-dataset", "{work}/ds", "--photons", "1e-300", "--sensor", "16", "16",
                    "--grid", "3", "3", "--n-train", "1", "--n-test", "1", "--quiet"),
         "--photons", 12, absent="measurement"),
    Case("fit-pairs-support-mask-all-zero", "psfkit",
         pairs_case(_save_array("mask.npy", np.zeros((16, 16), np.float32)), "fit-pairs",
                    "--support-mask", "{work}/mask.npy"), "mask.npy", 12),
    Case("fit-pairs-support-mask-nan", "psfkit",
         pairs_case(_save_array("mask.npy", np.full((16, 16), np.nan, np.float32)),
                    "fit-pairs", "--support-mask", "{work}/mask.npy"), "mask.npy", 12),

    # ---- class 13: paths resolved and contained ------------------------------------
    Case("pairs-json-scene-dir-parent", "psfkit", pairs_case(pairs_json('{"scene_dir": ".."}')),
         "scene_dir", 13),
    Case("pairs-json-scene-dir-link-outside", "psfkit",
         pairs_case(lambda p: ((p / "outside").symlink_to(p.parent),
                               (p / "pairs.json").write_text('{"scene_dir": "outside"}'))),
         "scene_dir", 13),

    # ---- class 14: a run folder holding foreign files is refused without --overwrite ---
    Case("train-into-folder-with-user-log", "ekdun",
         lambda work, fx: ((work / "run").mkdir(), (work / "run" / "log.csv").write_text("x"),
                           ekdun_case(*TRAIN)(work, fx))[-1], "run", 14),
    Case("train-into-the-data-folder", "ekdun",
         lambda work, fx: (shutil.copytree(fx.pairs, work / "pairs"),
                           ["train", str(work / "pairs"), str(work / "pairs"), "--kernels",
                            str(fx.kernels), "--quiet", "--epochs", "1", "--overwrite"])[-1],
         "training data", 14),

    # ---- class 7 (issue 21): messages that mislead ------------------------------------
    Case("admm-psf-all-zero", "ekdun",
         lambda work, fx: (_tiny_admm_inputs(work), np.save(work / "psf.npy",
                                                            np.zeros((32, 32), np.float32)),
                           ["admm", str(work / "psf.npy"), str(work / "meas.npy"), "--out",
                            str(work / "x.npy"), "--iterations", "2"])[-1],
         "psf.npy", 7, absent="psfkit-tmp"),
    Case("train-schedule-names-the-flag", "ekdun",
         ekdun_case(*TRAIN, "--schedule", "last-50"), "--schedule", 7, absent="eigen_last"),
    Case("fit-pairs-support-threshold-names-the-flag", "psfkit",
         pairs_case(None, "fit-pairs", "--support-threshold", "1"), "--support-threshold", 7,
         absent="support_threshold"),
    # ---- class 15 (issue 43): the last hostile inputs, each blamed on its cause ----------
    Case("register-out-empty", "psfkit",
         lambda work, fx: ["register", str(fx.grid), "--out", "", "--quiet"], "--out", 15),
    Case("fit-eigen-out-empty", "psfkit",
         lambda work, fx: ["fit-eigen", str(fx.grid), "--out=", "--quiet"], "--out", 15),
    Case("admm-out-empty", "ekdun",
         ekdun_case("admm", "{psf}", "{meas}", "--out", ""), "--out", 15),
    Case("make-dataset-folder-empty", "ekdun", ekdun_case("make-dataset", "", "--quiet"),
         "argument out", 15),
    Case("grid-of-1x1-frames-info", "psfkit", grid_case(prepare=_crop_frames(1)),
         "psf_r00_c00.tiff", 15),
    Case("grid-of-1x1-frames-register", "psfkit",
         grid_case(command="register", prepare=_crop_frames(1)), "psf_r00_c00.tiff", 15),
    Case("grid-of-11x11-frames-report", "psfkit",
         grid_case("--out", "{work}/rep", command="report", prepare=_crop_frames(11)),
         "too small to hold a PSF", 15),
    Case("eval-model-mono-kernels-rgb-pairs", "psfkit", _one_channel_kernels, "mono.npz", 15),
    Case("saturation-level-1e-300", "psfkit",
         grid_case("--saturation-level", "1e-300", command="register"), "--saturation-level",
         15, absent="% of the bright PSF"),
    Case("saturation-level-inside-the-psf", "psfkit",   # 12-bit data stored MSB-aligned
         grid_case("--saturation-level", "4095", command="mae"), "--saturation-level", 15,
         absent="% of the bright PSF"),
    Case("saturation-level-beyond-the-dtype", "psfkit",
         grid_case("--saturation-level", "70000", "--out", "{work}/k.npz",
                   command="fit-eigen"), "--saturation-level", 15),
    Case("make-dataset-photons-below-one", "ekdun",
         ekdun_case("make-dataset", "{work}/ds", "--photons", "0.5", "--quiet"), "--photons",
         15),
    Case("eval-model-kernels-huge-finite", "psfkit", kernel_case(kernels=_huge_kernel),
         "k.npz", 15, absent="errors.json"),
    Case("admm-kernels-huge-finite", "ekdun", admm_kernels_case(kernels=_huge_kernel),
         "k.npz", 15, absent="outdir"),
    # found by the sweep around them
    Case("report-over-its-own-grid", "psfkit",
         grid_case("--out", "{work}/grid", "--overwrite", command="report"),
         "is the input", 15),
    Case("report-over-the-folder-of-its-grid", "psfkit",
         grid_case("--out", "{work}", "--overwrite", command="report"), "holds the input", 15),
    Case("register-over-the-grids-manifest", "psfkit",
         grid_case("--out", "{work}/grid/manifest.json", "--overwrite", command="register"),
         "is part of the input", 15),
    Case("admm-over-its-measurement", "ekdun",
         ekdun_case("admm", "{psf}", "{meas}", "--out", "{meas}", "--overwrite"),
         "is the input", 15),
    Case("train-mono-kernels-rgb-pairs", "ekdun",
         lambda work, fx: (_one_channel_kernels(work, fx),
                           ["train", str(fx.pairs), str(work / "run"), "--kernels",
                            str(work / "mono.npz"), "--quiet", "--epochs", "1"])[-1],
         "mono.npz", 15),
    Case("admm-corner-background-of-a-tiny-measurement", "ekdun",
         lambda work, fx: (_tiny_admm_inputs(work),
                           np.save(work / "meas.npy", np.ones((8, 8), np.float32)),
                           ["admm", str(work / "psf.npy"), str(work / "meas.npy"), "--out",
                            str(work / "x.npy"), "--background", "corner"])[-1],
         "meas.npy: image of 8x8 px has no background corner", 15),
    Case("fit-pairs-of-2x2-images", "psfkit",
         pairs_case(lambda p: [np.save(f, np.load(f)[:2, :2]) for f in p.rglob("*.npy")],
                    "fit-pairs"), "2x2 px pairs", 15, absent="kernel model"),
    Case("fit-pairs-downsample-to-2x2", "psfkit",
         pairs_case(None, "fit-pairs", "--downsample", "8"), "--downsample 8", 15),
    Case("black-level-above-the-signal", "psfkit",
         grid_case(command="register", prepare=lambda g: (
             _edit_manifest(g, lambda d: (d.pop("dark_frame"), d.update(black_level=65000))),
             (g / "dark.tiff").unlink())), "black_level 65000", 15, absent="no point-source"),
    Case("admm-kernels-tiny-finite", "ekdun",
         admm_kernels_case(kernels=lambda k: (k * np.float32(1e-30)).astype(np.float32)),
         "k.npz", 15, absent="outdir"),
    Case("fit-pairs-scenes-1e30", "psfkit",
         pairs_case(lambda p: [np.save(f, np.load(f) * np.float32(1e30))
                               for f in (p / "scene").glob("*.npy")], "fit-pairs"),
         "times the light of their scenes", 15, absent="kernel model"),
    Case("train-kernels-huge-finite", "ekdun",
         lambda work, fx: (_rewrite_kernels(fx.kernels, work / "k.npz", kernels=_huge_kernel),
                           ["train", str(fx.pairs), str(work / "run"), "--kernels",
                            str(work / "k.npz"), "--quiet", "--epochs", "1"])[-1],
         "k.npz", 15),
]


# --------------------------------------------------------------------------- fixtures


def _float_grid(src: Path, dst: Path) -> Path:
    import tifffile

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("ground_truth"))
    for f in dst.glob("*.tiff"):
        _write_tiff(f, tifffile.imread(f).astype(np.float32))
    _edit_manifest(dst, lambda doc: doc.pop("bit_depth"))
    return dst


@pytest.fixture(scope="module")
def fixtures(grid_3x3, tiny_data, tmp_path_factory) -> Fixtures:
    from ekdun.data.pairs import PairsDataset
    from ekdun.training import TrainOptions, train
    from ekdun.training.trainer import CHECKPOINT

    pairs, kernels = tiny_data
    root = tmp_path_factory.mktemp("bad_inputs_fixtures")
    options = TrainOptions(epochs=1, batch_size=4, progress=False, threads=1)
    runs = {}
    for name, overrides in (("ekdun", SMALL_EKDUN), ("le-admm-u", SMALL_LE_ADMM)):
        train(root / name, name, kernels, PairsDataset(pairs), "tiny", overrides, options)
        runs[name] = root / name / CHECKPOINT
    return Fixtures(grid=grid_3x3, float_grid=_float_grid(grid_3x3, root / "float_grid"),
                    pairs=pairs, kernels=kernels, checkpoint=runs["ekdun"],
                    le_admm=runs["le-admm-u"])


def _listing(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_size for p in sorted(folder.rglob("*"))
            if p.is_file()} | {str(p.relative_to(folder)) + "/": 0
                               for p in folder.rglob("*") if p.is_dir()}


#: Runs ``argv[2:]`` as its only child and writes the child's peak resident memory (bytes) to
#: the file ``argv[1]``; a fresh process, so that no earlier child of pytest counts.
PEAK_WRAPPER = """
import resource, subprocess, sys
done = subprocess.run(sys.argv[2:])
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
scale = 1 if sys.platform == "darwin" else 1024   # bytes on macOS, kilobytes on Linux
open(sys.argv[1], "w").write(str(peak * scale))
sys.exit(done.returncode)
"""
BOMB_PEAK_BYTES = 2**30


def _run(cli: str, args: list[str], peak_file: Path | None = None
         ) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    for key in ("PSFKIT_DEBUG", "EKDUN_DEBUG"):
        env.pop(key, None)
    module = "psfkit.cli" if cli == "psfkit" else "ekdun.cli"
    command = [sys.executable, "-m", module, *args]
    if peak_file is not None:
        command = [sys.executable, "-c", PEAK_WRAPPER, str(peak_file), *command]
    return subprocess.run(command, capture_output=True, text=True, env=env, cwd=REPO,
                          timeout=300)


def test_table_is_large_and_covers_every_class():
    assert len(CASES) >= 60
    assert len({c.id for c in CASES}) == len(CASES)
    # class 6 (leftovers after a kill) is tested by tests/e2e/test_output_policy.py
    assert {c.cls for c in CASES} == {1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 12, 13, 14, 15}


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_is_one_line_naming_the_culprit(case: Case, fixtures: Fixtures,
                                                  tmp_path: Path) -> None:
    work = tmp_path / "case"
    work.mkdir()
    args = case.build(work, fixtures)
    before = _listing(work)
    peak_file = tmp_path / "peak" if case.bomb else None
    done = _run(case.cli, args, peak_file)
    assert "Traceback" not in done.stderr + done.stdout
    lines = done.stderr.splitlines()
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    assert len(lines) == 1 and lines[0].strip(), lines
    assert lines[0].startswith(f"{case.cli}"), lines[0]
    assert case.names in lines[0], lines[0]
    assert "internal error" not in lines[0]
    assert not case.absent or case.absent not in lines[0], lines[0]
    assert _listing(work) == before, "the failed command left output behind"
    if peak_file is not None:
        peak = int(peak_file.read_text())
        print(f"{case.id}: peak resident memory {peak / 2**20:.0f} MiB")
        assert 0 < peak < BOMB_PEAK_BYTES, f"{case.id}: peak {peak / 2**20:.0f} MiB"


# --------------------------------------------------------------------------- outputs


def test_non_finite_outputs_are_refused_before_writing(tmp_path):
    from psfkit.errors import InvalidInputError, ModelFileError
    from psfkit.forward.kernelfile import KernelModel, save_kernels
    from psfkit.io.images import write_image
    from psfkit.io.json_documents import dumps_finite
    from psfkit.io.validation import require_finite_output

    with pytest.raises(InvalidInputError, match=r"out\.json.*non-finite.*at a\.b\.1"):
        dumps_finite({"a": {"b": [1.0, float("nan")]}}, "out.json")
    with pytest.raises(InvalidInputError, match="non-finite"):
        dumps_finite({"x": np.float32(np.inf)}, "t.json", default=float)
    assert json.loads(dumps_finite({"a": [1.0, None]}, "ok.json")) == {"a": [1.0, None]}
    with pytest.raises(InvalidInputError, match="refusing to write 2 non-finite"):
        require_finite_output(np.array([0.0, np.nan, np.inf]), "x.npy")
    image = np.ones((1, 8, 8), np.float32)
    image[0, 2, 2] = np.nan
    with pytest.raises(InvalidInputError, match=r"x\.npy"):
        write_image(tmp_path / "x.npy", image)
    kernels = np.ones((1, 1, 4, 4), np.float32)
    with pytest.raises(ModelFileError, match="NaN/Inf"):
        KernelModel(kernels=np.where(kernels > 0, np.nan, 0), basis="si", channels=("L",))
    with pytest.raises(ModelFileError, match="optical_center"):
        KernelModel(kernels=kernels, basis="si", channels=("L",), sensor_shape=(8, 8),
                    optical_center=(float("nan"), 4.0))
    model = KernelModel(kernels=kernels, basis="si", channels=("L",), sensor_shape=(8, 8),
                        optical_center=(4.0, 4.0))
    object.__setattr__(model, "optical_center", (float("nan"), 4.0))   # spoiled later
    with pytest.raises(ModelFileError, match=r"k\.npz.*optical_center"):
        save_kernels(tmp_path / "k.npz", model)
    assert list(tmp_path.iterdir()) == []


def test_debug_shows_the_traceback_and_internal_errors_say_so(tmp_path, capsys, monkeypatch):
    from psfkit.cli.main import error_line

    line, status = error_line("psfkit", KeyError("boom"))
    assert status == 1 and "internal error" in line and "report" in line
    assert error_line("psfkit", RecursionError())[1] == 2
    assert error_line("psfkit", zipfile.BadZipFile("x"))[1] == 2
    done = subprocess.run([sys.executable, "-m", "psfkit.cli", "--debug", "info",
                           str(tmp_path / "missing")], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, cwd=REPO, timeout=120)
    assert done.returncode != 0 and "Traceback" in done.stderr and "GridFormatError" in done.stderr


def _numeric_actions(parser: Any, prog: str) -> list[tuple[str, Any]]:
    """``(command flag, action)`` of every option of ``parser`` and its sub-commands that
    converts its value (``type=``), other than ``--device`` (a name, see ``device_name``)."""
    import argparse

    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found += _numeric_actions(sub, f"{prog} {name}")
        elif action.type is not None and action.option_strings:
            found.append((f"{prog} {action.option_strings[0]}", action))
    return found


def test_every_numeric_flag_of_both_clis_takes_its_range_from_its_table():
    from ekdun.cli import build_parser as ekdun_parser
    from ekdun.flag_ranges import FLAGS as EKDUN_FLAGS
    from ekdun.flag_ranges import device_name
    from psfkit.cli.main import build_parser as psfkit_parser
    from psfkit.io.flag_ranges import FLAGS as PSFKIT_FLAGS

    actions = [(where, action, PSFKIT_FLAGS)
               for where, action in _numeric_actions(psfkit_parser(), "psfkit")]
    actions += [(where, action, EKDUN_FLAGS)
                for where, action in _numeric_actions(ekdun_parser(), "ekdun")]
    assert len(actions) > 40
    for where, action, table in actions:
        if action.option_strings[0] == "--device":
            assert action.type is device_name, where
            continue
        spec = getattr(action.type, "flag_range", None)
        assert spec is not None, f"{where}: its type is not from its CLI's flag table"
        assert spec in table.values(), where
        assert spec.high is not None, f"{where}: no upper bound"


def test_warnings_and_library_logging_never_reach_stderr(capsys):
    """The runner collects them for every command: a failing command prints its one line,
    a succeeding one nothing of theirs."""
    import argparse
    import logging
    import warnings

    from psfkit.cli.main import run_cli
    from psfkit.errors import InvalidInputError

    def noisy(args: argparse.Namespace) -> int:
        np.log(np.zeros(1))                                   # numpy RuntimeWarning
        warnings.warn("a library's UserWarning", UserWarning, stacklevel=1)
        logging.getLogger("tifffile").warning("a library's log record")
        if args.fail:
            raise InvalidInputError("bad\nname.npy: refused")
        return 0

    parser = argparse.ArgumentParser(prog="psfkit")
    parser.add_argument("--fail", action="store_true")
    parser.set_defaults(func=noisy)
    assert run_cli("psfkit", parser, []) == 0
    assert capsys.readouterr().err == ""
    assert run_cli("psfkit", parser, ["--fail"]) == 2
    assert capsys.readouterr().err == "psfkit: error: bad\\nname.npy: refused\n"


def test_kernel_files_of_zeros_are_refused_when_written(tmp_path):
    from psfkit.errors import ModelFileError
    from psfkit.forward.kernelfile import KernelModel, save_kernels

    with pytest.raises(ModelFileError, match="every kernel is zero"):
        save_kernels(tmp_path / "k.npz", KernelModel(kernels=np.zeros((1, 1, 4, 4), np.float32),
                                                     basis="si", channels=("L",)))
    assert list(tmp_path.iterdir()) == []
