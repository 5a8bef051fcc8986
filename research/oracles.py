r"""The eigen-kernel oracles of a virtual bench: the best eigen-kernel model, known from the
simulator (issue 23, item 1). ``ekdun.data.oracle`` until issue 44: a research instrument, not
installed with the product.

The virtual bench knows the truth: the noise-free PSF of every grid node and the dense
shift-variant operator ``A_dense`` that makes its measurements (:mod:`ekdun.data.dense_model`).
For a weight basis and convention it defines two "best" eigen-kernel models:

**operator oracle** (:func:`operator_oracle`, the main one)
    the kernels minimising the expected prediction error over the dataset's own scene
    distribution, noise-free,

    .. math::

        K^\star = \arg\min_K\ \mathbb E_x\,\lVert A_\mathrm{dense}\,x - A_K\,x\rVert^2
        \approx \arg\min_K \sum_{i=1}^{n}\lVert A_\mathrm{dense}\,x_i - A_K\,x_i\rVert^2 ,

    with ``n`` fresh scenes of :func:`~ekdun.data.virtual_bench.make_scenes` (a random stream
    of their own, not the training scenes), solved to convergence by the exact pairs solver
    (:mod:`psfkit.fitting.pairs.solver`: no ridge, no prior, no constraint, no per-pair scale). Its
    convergence in ``n`` is measured: the same solve on the first ``n/2`` scenes, and the
    difference-kernel NCC between the two (``convergence`` in the result);

**PSF oracle** (:func:`psf_oracle`)
    the grid fit of :mod:`psfkit.fitting.grid.eigen` (the closed-form per-pixel fit behind ``psfkit
    fit-eigen``) of the noise-free node PSFs at their true chief-ray positions
    (:func:`~ekdun.data.virtual_bench.node_psfs`): no registration, no noise, no normalisation.

Both are kernel files (:class:`psfkit.forward.kernelfile.KernelModel`) in the dense model's units
(measurement per unit scene radiance), readable by ``python -m research.compare``,
``psfkit eval-model`` and ``ekdun train --kernels``. :func:`compare_oracles` says how much two
models differ (difference-kernel NCC, kernel error, prediction error on noise-free test pairs).

``python -m research.oracle DATASET --write-dataset`` (:func:`write_dataset_oracles`) writes the
unconstrained oracles of both conventions into an existing dataset, ``DATASET/oracle/``, and
lists them in its manifest; :func:`oracle_file` finds them (``ekdun make-dataset`` wrote them
until issue 44; such datasets still list theirs).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ekdun.data.bench_spec import (
    VirtualBenchSpec,
    dense_model_for,
    make_scenes,
    node_psfs,
)
from ekdun.data.dense_model import hat_weights
from ekdun.data.virtual_bench import MANIFEST, _data_files, content_hash, read_manifest
from ekdun.errors import ConfigurationError, InvalidInputError
from psfkit.fitting.pairs.batches import PairBatches
from psfkit.fitting.pairs.constraints import projected_newton
from psfkit.fitting.pairs.fit import predict
from psfkit.fitting.pairs.options import NEWTON_CG_ITERATIONS, NEWTON_ITERATIONS
from psfkit.fitting.pairs.solver import regularised_normal, solve_kernels
from psfkit.forward.geometry import CONVENTIONS
from psfkit.forward.kernelfile import KernelModel, save_kernels
from psfkit.forward.weights import get_basis
from psfkit.io.atomic import atomic_directory, atomic_file
from research.compare.statistics import normalized_correlation

#: Random stream of the oracle's scenes (train 0, test 1): same distribution, new scenes.
ORACLE_STREAM = 2
#: Random stream of the noise-free test scenes the oracles are compared on.
COMPARE_STREAM = 3
#: Default relative residual of the oracle's normal equations (float64).
ORACLE_TOLERANCE = 1e-7
#: Default Newton steps, CG iterations per step and KKT tolerance of the non-negative oracle.
NONNEG_ITERATIONS = NEWTON_ITERATIONS
NONNEG_CG_ITERATIONS = NEWTON_CG_ITERATIONS
NONNEG_TOLERANCE = 1e-10   # an oracle: tighter than fit-pairs' NEWTON_TOLERANCE

Forward = Callable[[Tensor], Tensor]


def default_oracle_scenes(spec: VirtualBenchSpec) -> int:
    """Scenes of the operator oracle by default: 4 × the training pairs, at least 128."""
    return max(128, 4 * spec.n_train)


@dataclass
class OracleResult:
    """An oracle model and how it was obtained.

    ``record`` is what the dataset manifest keeps (JSON-able): kind, scenes, solver
    iterations and relative residual, the relative prediction error of the oracle on its own
    scenes, and (operator oracle) its convergence between ``n/2`` and ``n`` scenes.
    """

    model: KernelModel
    record: dict[str, Any] = field(default_factory=dict)


def oracle_scenes(spec: VirtualBenchSpec, count: int, stream: int = ORACLE_STREAM
                  ) -> np.ndarray:
    """``count`` scenes ``(n, 3, H', W')`` of the dataset's training distribution, from a
    random stream of their own."""
    return make_scenes(spec, "train", count=count, stream=stream)


def _dense_forward(spec: VirtualBenchSpec) -> Forward:
    model = dense_model_for(spec)
    return lambda x: model(x)


def _kernel_model(kernels: np.ndarray, basis: str, convention: str,
                  spec: VirtualBenchSpec, provenance: dict[str, Any]) -> KernelModel:
    return KernelModel(kernels=np.asarray(kernels, dtype=np.float32), basis=basis,
                       convention=convention, sensor_shape=spec.sensor_shape,
                       channels=("R", "G", "B"),
                       normalization="dense bench model units: measurement per unit scene "
                                     "radiance (no normalisation)",
                       provenance=provenance)


def operator_oracle(spec: VirtualBenchSpec, convention: str, basis: str = "paper",
                    n_scenes: int | None = None, forward: Forward | None = None,
                    tolerance: float = ORACLE_TOLERANCE, max_iterations: int = 3000,
                    batch_size: int | None = None, check_convergence: bool = True,
                    scenes: np.ndarray | None = None, nonneg: bool = False,
                    projected_iterations: int = NONNEG_ITERATIONS,
                    projected_tolerance: float = NONNEG_TOLERANCE,
                    cg_iterations: int = NONNEG_CG_ITERATIONS,
                    start: np.ndarray | None = None, progress: bool = False) -> OracleResult:
    """The eigen-kernel model closest to the dense operator over the scene distribution.

    Parameters
    ----------
    spec : VirtualBenchSpec
        The bench (its dense model, scene distribution and sensor).
    convention : {"source", "sensor"}
        Convention of the eigen-kernel model (the dense model keeps ``spec.convention``).
    basis : str
        Weight basis (default the paper's).
    n_scenes : int, optional
        Scenes (default :func:`default_oracle_scenes`).
    forward : callable, optional
        ``(B, C, H', W')`` float64 scenes → noise-free measurements; default the bench's dense
        model. (Tests pass an exact eigen-kernel model, whose oracle is itself.)
    tolerance, max_iterations
        Of the preconditioned CG (relative residual of the normal equations).
    check_convergence : bool
        Also solve on the first half of the scenes and record the agreement.
    scenes : numpy.ndarray, optional
        ``(n, C, H', W')`` scenes to use instead of the dataset's distribution (e.g.
        :func:`white_scenes`: the oracle of a flat scene spectrum); ``n_scenes`` is then
        ignored.
    nonneg : bool
        Minimise over non-negative kernels: projected Newton-CG
        (:func:`psfkit.fitting.pairs.constraints.projected_newton`) on the same normal equations,
        warm-started from the unconstrained oracle, for at most ``projected_iterations``
        Newton steps of ``cg_iterations`` preconditioned CG iterations each (on float32
        products, with float64 gradients and line search), or until the relative KKT
        residual (``kkt_residual`` of :func:`psfkit.fitting.pairs.constraints.projected_newton`:
        ``‖K − max(0, K − ∇/L)‖ / ‖K‖``
        per channel, the largest) is below ``projected_tolerance``. The record gives both.
    start : numpy.ndarray, optional
        ``(K, C, H, W)`` kernels to warm-start the unconstrained solve from (e.g. the
        unconstrained oracle, for the non-negative one); the same minimiser, fewer CG
        iterations. Ignored by the half-scenes convergence check.
    progress : bool
        Progress bars for the CG and Newton iterations (stderr).

    Returns
    -------
    OracleResult
    """
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    forward = forward or _dense_forward(spec)
    if scenes is None:
        n = n_scenes or default_oracle_scenes(spec)
        x = oracle_scenes(spec, n)
        scene_record: Any = ORACLE_STREAM
    else:
        x = np.asarray(scenes)
        if x.ndim != 4 or x.shape[2:] != tuple(spec.sensor_shape):
            raise ValueError(f"scenes must be (n, C, {spec.sensor_shape[0]}, "
                             f"{spec.sensor_shape[1]}), got {x.shape}")
        n, scene_record = len(x), "given"
    h, w = spec.sensor_shape

    def measurements(start: int, stop: int) -> Tensor:
        with torch.no_grad():
            return forward(torch.as_tensor(x[start:stop], dtype=torch.float64))

    record: dict[str, Any] = {"kind": "operator", "basis": basis, "convention": convention,
                              "dense_convention": spec.convention, "n_scenes": n,
                              "scene_stream": scene_record, "tolerance": tolerance}
    if start is not None:
        record["warm_start"] = True

    def bar(total: int, what: str) -> Any:
        if not progress:
            return None
        from tqdm.auto import tqdm

        return tqdm(total=total, unit="it", leave=False, desc=what)

    def solve(scenes_: np.ndarray, first: Tensor | None, what: str
              ) -> tuple[Tensor, Any, dict[str, Any] | None, PairBatches]:
        batches = PairBatches(scenes_, basis, convention, (h, w), batch_size=batch_size)
        cg = bar(max_iterations, f"oracle CG ({what})")
        kernels, info, system = solve_kernels(batches, measurements, start=first,
                                              tolerance=tolerance,
                                              max_iterations=max_iterations, bar=cg)
        if cg is not None:
            cg.close()
        projected = None
        if nonneg:
            hessian = regularised_normal(batches.astype(torch.float32), system["lambda"],
                                         system["mu"])
            newton = bar(projected_iterations, f"oracle Newton ({what})")
            kernels, projected = projected_newton(
                system["normal"], system["rhs"], kernels, system["precondition"],
                projected_iterations, cg_iterations, projected_tolerance, bar=newton,
                hessian=hessian)
            if newton is not None:
                newton.close()
        return kernels, info, projected, batches

    if start is not None:
        start = np.asarray(start)
        k = get_basis(basis).n_kernels
        if start.ndim != 4 or start.shape[0] != k or start.shape[2:] != (h, w):
            raise ValueError(f"start must be (K, C, {h}, {w}) kernels of the {basis!r} basis, "
                             f"got {start.shape}")
    half = None
    if check_convergence and n >= 2:
        half, info_half, _, _ = solve(x[: n // 2], None, f"{n // 2} scenes")
    first = half if start is None else torch.as_tensor(start, dtype=torch.float64)
    kernels, info, projected, batches = solve(x, first, f"{n} scenes")
    err, norm, _num, _den = batches.residual_norms(kernels, measurements)
    record.update(iterations=info.iterations, relative_residual=info.relative_residual,
                  converged=info.converged,
                  relative_prediction_error=float((err / norm).mean()))
    if projected is not None:
        record["kind"] = "operator, non-negative"
        record["projected"] = {k: projected[k] for k in ("method", "iterations", "kkt_residual",
                                                         "converged")}
        record["projected"]["cg_iterations"] = cg_iterations
    if half is not None:
        record["convergence"] = {
            "scenes": [n // 2, n],
            **{f"{k}_difference_ncc": v for k, v in
               difference_nccs(half.numpy(), kernels.numpy(), basis).items()},
            "kernel_change": float((half - kernels).norm() / kernels.norm()),
            "iterations_half": info_half.iterations}
    provenance = {"source": "ekdun oracle (operator)", **record}
    return OracleResult(_kernel_model(kernels.numpy(), basis, convention, spec, provenance),
                        record)


def psf_oracle(spec: VirtualBenchSpec, convention: str, basis: str = "paper",
               ridge: float | None = None) -> OracleResult:
    """The grid fit of the noise-free node PSFs at their true chief-ray positions.

    The per-pixel least squares of :mod:`psfkit.fitting.grid.eigen` (``psfkit fit-eigen``'s
    solver), fed
    with each node's noise-free PSF re-centred on its chief ray (full valid mask) and the true
    chief-ray shift; ``ridge`` defaults to fit-eigen's.
    """
    from psfkit.fitting.grid.eigen import DEFAULT_RIDGE, NormalEquations

    kernels, shifts, _rows, _cols = node_psfs(spec)
    n, m, c, h, w = kernels.shape
    equations = NormalEquations(get_basis(basis), convention, (c, h, w))
    valid = np.ones((h, w), bool)
    for r in range(n):
        for q in range(m):
            equations.add(kernels[r, q], valid, (float(shifts[r, q, 0]),
                                                 float(shifts[r, q, 1])))
    ridge = DEFAULT_RIDGE if ridge is None else ridge
    fitted, _ = equations.solve(ridge, conditioning=False)
    record = {"kind": "psf", "basis": basis, "convention": convention,
              "nodes": [n, m], "ridge": ridge}
    return OracleResult(_kernel_model(fitted, basis, convention, spec,
                                      {"source": "ekdun oracle (psf)", **record}), record)


def white_scenes(spec: VirtualBenchSpec, count: int, seed: int = 0) -> np.ndarray:
    """``count`` scenes ``(n, 3, H', W')`` float32 of independent standard-normal pixels: a
    flat scene spectrum, every spatial frequency weighted alike (zero mean, so that no DC
    term favours the flat scene; the least squares does not need non-negative scenes)."""
    rng = np.random.default_rng([spec.seed, ORACLE_STREAM, 1000 + seed])
    return rng.standard_normal((count, 3, *spec.sensor_shape), dtype=np.float32)


def dense_psf_oracle(spec: VirtualBenchSpec, convention: str, basis: str = "paper",
                     step: int = 1, crop: bool = False,
                     ridge: float | None = None) -> OracleResult:
    r"""The grid fit of the dense model's PSF at *every* scene pixel (every ``step``-th).

    The PSF of scene pixel ``p`` is the dense model's interpolation
    ``h_p = Σ_n w_n(p) K_n`` (:mod:`ekdun.data.dense_model`), at the chief-ray shift of ``p``
    itself. Where :func:`psf_oracle` weights the 81 grid nodes, this weights every point of
    the field alike. With ``crop=True`` each PSF counts only where it lands on the sensor
    (the rectangle ``0 ≤ p + d < (H', W')`` of kernel offsets ``d``): for a source-side dense
    model this is the operator oracle for scenes of a flat spectrum (:func:`white_scenes`,
    independent zero-mean pixels of unit variance), in expectation, since then
    ``E‖crop((A_dense − A_K) x)‖² = Σ_p ‖mask_p ⊙ (h_p − Σ_k W_k(p) K_k)‖²``. The steps
    PSF oracle → dense PSF oracle → with the crop → operator oracle (white scenes) → operator
    oracle (the dataset's scenes) split the distance between the two oracles into its causes
    (``research/oracle_gap.py``).
    """
    from psfkit.fitting.grid.eigen import DEFAULT_RIDGE, NormalEquations

    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    kernels, _shifts, rows, cols = node_psfs(spec)
    n, m, c, h, w = kernels.shape
    wr, wc = hat_weights(rows, h), hat_weights(cols, w)     # (N, H), (M, W): the dense model's
    equations = NormalEquations(get_basis(basis), convention, (c, h, w))
    valid = np.ones((h, w), bool)
    flat = kernels.reshape(n, m, -1)
    for i in range(0, h, step):
        # the row's interpolation over node rows, once per row
        row_mix = np.tensordot(wr[:, i], flat, axes=(0, 0))          # (M, C·H·W)
        for j in range(0, w, step):
            psf = (wc[:, j] @ row_mix).reshape(c, h, w)
            if crop:
                # kernel pixel (a, b) lands on sensor pixel (i + a − h//2, j + b − w//2)
                valid = np.zeros((h, w), bool)
                valid[max(0, h // 2 - i):min(h, h + h // 2 - i),
                      max(0, w // 2 - j):min(w, w + w // 2 - j)] = True
            equations.add(psf, valid, (float(j - w // 2), float(i - h // 2)))
    ridge = DEFAULT_RIDGE if ridge is None else ridge
    fitted, _ = equations.solve(ridge, conditioning=False)
    record = {"kind": "dense_psf", "basis": basis, "convention": convention, "step": step,
              "crop": crop, "points": equations.count, "ridge": ridge}
    return OracleResult(_kernel_model(fitted, basis, convention, spec,
                                      {"source": "ekdun oracle (dense psf)", **record}), record)


def difference_nccs(a: np.ndarray, b: np.ndarray, basis: str = "paper") -> dict[str, float]:
    """Uncentred NCC of ``K_k − K_0`` between two kernel stacks (all channels), per
    correction kernel (``v``, ``h`` for the paper basis), and of the base kernels."""
    names = get_basis(basis).kernel_names
    out = {"base": normalized_correlation(a[0], b[0])}
    for k in range(1, len(a)):
        out[names[k]] = normalized_correlation(a[k] - a[0], b[k] - b[0])
    return out


def compare_oracles(a: KernelModel, b: KernelModel, spec: VirtualBenchSpec,
                    n_test: int = 32, forward: Forward | None = None,
                    labels: tuple[str, str] = ("a", "b")) -> dict[str, Any]:
    """How much two eigen-kernel models differ: difference-kernel and base NCC, kernel error
    ``‖a − b‖/‖b‖``, and the mean relative prediction errors of both against the dense model
    (and of ``a`` against ``b``) on ``n_test`` noise-free test pairs (new scenes)."""
    forward = forward or _dense_forward(spec)
    x = oracle_scenes(spec, n_test, stream=COMPARE_STREAM)
    with torch.no_grad():
        y = forward(torch.as_tensor(x, dtype=torch.float64)).numpy()
    pa = predict(a, x, dtype=torch.float64)
    pb = predict(b, x, dtype=torch.float64)

    def rel(p: np.ndarray, q: np.ndarray) -> float:
        axes = (1, 2, 3)
        return float(np.mean(np.sqrt(((p - q) ** 2).sum(axes) / (q**2).sum(axes))))

    ka, kb = a.kernels.astype(np.float64), b.kernels.astype(np.float64)
    return {"difference_ncc": difference_nccs(ka, kb, a.basis),
            "kernel_error": float(np.linalg.norm(ka - kb) / np.linalg.norm(kb)),
            "prediction_error": {labels[0]: rel(pa, y), labels[1]: rel(pb, y),
                                 f"{labels[0]}_vs_{labels[1]}": rel(pa, pb)},
            "n_test": n_test}


def write_oracles(folder: Path, spec: VirtualBenchSpec, basis: str = "paper",
                  n_scenes: int | None = None, progress: bool = False) -> dict[str, Any]:
    """Write ``{basis}_{convention}.npz`` (operator oracle) and ``psf_{basis}_{convention}.npz``
    (PSF oracle) for both conventions into ``folder``; returns the manifest's record.
    ``progress``: the operator oracles' progress bars (stderr)."""
    folder.mkdir(parents=True, exist_ok=True)
    dense = _dense_forward(spec)
    out: dict[str, Any] = {"basis": basis, "dense_convention": spec.convention, "files": {}}
    for convention in CONVENTIONS:
        op = operator_oracle(spec, convention, basis, n_scenes, forward=dense,
                             progress=progress)
        psf = psf_oracle(spec, convention, basis)
        name, psf_name = f"{basis}_{convention}.npz", f"psf_{basis}_{convention}.npz"
        save_kernels(folder / name, op.model)
        save_kernels(folder / psf_name, psf.model)
        out["files"][convention] = {
            "operator": name, "psf": psf_name, "operator_record": op.record,
            "psf_record": psf.record,
            "psf_vs_operator": compare_oracles(psf.model, op.model, spec, forward=dense,
                                               labels=("psf", "operator"))}
    return out


def oracle_file(root: str | os.PathLike, convention: str, kind: str = "operator"
                ) -> Path | None:
    """The oracle kernel file of ``convention`` that a virtual-bench dataset lists.

    Parameters
    ----------
    root : path-like
        Dataset folder (``ekdun make-dataset``).
    convention : {"source", "sensor"}
        Weight convention of the eigen-kernel model to compare with.
    kind : {"operator", "psf"}
        The operator oracle (the best eigen-kernel model of the simulator, the default) or the
        PSF oracle.

    Returns
    -------
    pathlib.Path or None
        ``root/oracle/<file>``; ``None`` when ``root`` is not a virtual-bench dataset, has no
        oracles (:func:`write_dataset_oracles` writes them) or lists none of that convention.
    """
    if kind not in ("operator", "psf"):
        raise ValueError(f"kind must be 'operator' or 'psf', got {kind!r}")
    doc = read_manifest(root)
    files = ((doc or {}).get("oracle") or {}).get("files") or {}
    name = (files.get(convention) or {}).get(kind)
    return None if not name else Path(root) / "oracle" / name


def dataset_spec(root: str | os.PathLike) -> tuple[dict[str, Any], VirtualBenchSpec]:
    """``(manifest, spec)`` of a virtual-bench dataset.

    Raises
    ------
    InvalidInputError
        ``root`` is not a virtual-bench dataset, or its manifest's spec is not valid (one
        line naming the manifest).
    """
    manifest = read_manifest(root)
    if manifest is None or "spec" not in manifest:
        raise InvalidInputError(f"{root}: not a virtual-bench dataset (no {MANIFEST} from "
                                "ekdun make-dataset)")
    try:
        spec = VirtualBenchSpec.from_dict(manifest["spec"])
    except (TypeError, ConfigurationError) as exc:   # an edited manifest: name it
        raise InvalidInputError(f"{Path(root) / MANIFEST}: spec: {exc}") from None
    return manifest, spec


def dataset_oracle_scenes(manifest: dict[str, Any]) -> int | None:
    """Scenes of the operator oracle a dataset already has: those of the oracle its manifest
    lists, else the ``oracle_scenes`` of a manifest written before issue 44 (``make-dataset
    --oracle-scenes``), else ``None`` (:func:`default_oracle_scenes`)."""
    files = (manifest.get("oracle") or {}).get("files") or {}
    for entry in files.values():
        n = (entry.get("operator_record") or {}).get("n_scenes")
        if n:
            return int(n)
    return int((manifest.get("spec") or {}).get("oracle_scenes") or 0) or None


def _listed_oracles_exist(root: Path, manifest: dict[str, Any], n_scenes: int) -> bool:
    files = (manifest.get("oracle") or {}).get("files") or {}
    if set(files) != set(CONVENTIONS):
        return False
    return all((entry.get("operator_record") or {}).get("n_scenes") == n_scenes
               and all((root / "oracle" / entry[k]).is_file() for k in ("operator", "psf"))
               for entry in files.values())


def write_dataset_oracles(root: str | os.PathLike, n_scenes: int | None = None,
                          basis: str = "paper", progress: bool = False
                          ) -> tuple[dict[str, Any], bool]:
    """Write the unconstrained operator and PSF oracles of both conventions into a dataset.

    ``root/oracle/`` gets ``{basis}_{convention}.npz`` and ``psf_{basis}_{convention}.npz``
    (:func:`write_oracles`), the manifest an ``oracle`` record (what :func:`oracle_file`
    reads) and its file list and content hash anew, so that ``ekdun make-dataset`` of the same
    spec still reuses the dataset. The folder is written atomically and replaced as a whole;
    the manifest is replaced atomically after it (a crash in between leaves a dataset whose
    manifest does not list the new files: make-dataset rebuilds it, nothing reads a half
    oracle).

    Parameters
    ----------
    root : path-like
        A virtual-bench dataset (``ekdun make-dataset``).
    n_scenes : int, optional
        Scenes of the operator oracle (default :func:`dataset_oracle_scenes`, else
        :func:`default_oracle_scenes`).
    basis : str
        Weight basis.
    progress : bool
        Progress bars of the solves (stderr).

    Returns
    -------
    (dict, bool)
        The manifest's ``oracle`` record, and whether it was computed (``False``: the dataset
        already had these oracles, of the same scenes, and nothing was written).
    """
    root = Path(root)
    manifest, spec = dataset_spec(root)
    n = n_scenes or dataset_oracle_scenes(manifest) or default_oracle_scenes(spec)
    if manifest.get("oracle", {}).get("basis") == basis and \
            _listed_oracles_exist(root, manifest, n):
        return manifest["oracle"], False
    with atomic_directory(root / "oracle", overwrite=True) as tmp:
        record = write_oracles(tmp, spec, basis, n_scenes=n, progress=progress)
    # the dataset's own listing (every file but the manifest): the cache check's
    files = _data_files(root)
    manifest.update(oracle=record, files=files, content_hash=content_hash(root, files))
    with atomic_file(root / MANIFEST) as out:
        out.write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return record, True


__all__ = ["COMPARE_STREAM", "ORACLE_STREAM", "ORACLE_TOLERANCE", "OracleResult",
           "compare_oracles", "dataset_oracle_scenes", "dataset_spec", "default_oracle_scenes",
           "dense_psf_oracle", "difference_nccs", "operator_oracle", "oracle_file",
           "oracle_scenes", "psf_oracle", "white_scenes", "write_dataset_oracles",
           "write_oracles"]
