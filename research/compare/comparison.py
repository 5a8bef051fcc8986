"""Comparing kernel models with the measured modes (:func:`compare_kernels`,
:func:`compare_model`): displacement maps, difference kernels and spans."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from psfkit.calibration.preprocess import luminance
from psfkit.calibration.registration import register_shift, shift_image
from psfkit.errors import ModelFileError
from psfkit.fitting.grid.pca import principal_angles_deg
from psfkit.forward.kernelfile import KernelModel, load_kernels
from psfkit.io.grid import PsfGrid
from research.compare.displacement import (
    DisplacementMap,
    caustic_support,
    comparison_mask,
    displacement_map,
)
from research.compare.kernel_change import split_kernel_changes
from research.compare.measured import MeasuredModes, measure_modes, modes_from_kernel_file
from research.compare.options import CompareOptions
from research.compare.resampling import pad_kernels, resample
from research.compare.results import KernelComparison, KernelSetComparison
from research.compare.statistics import map_agreement, normalized_correlation


def _kernel_displacements(lum: np.ndarray, names: tuple[str, ...], mask: np.ndarray,
                          options: CompareOptions) -> dict[str, DisplacementMap]:
    return {name: displacement_map(lum[0], lum[k], mask, options.flow_method, options.smooth_px)
            for k, name in enumerate(names) if k > 0}


def _prepare_learned(learned: KernelModel, measured: MeasuredModes, options: CompareOptions,
                     where: str) -> tuple[np.ndarray, tuple[float, float]]:
    """Learned kernels padded to the sensor and registered to the measured ``Kbase``."""
    if learned.basis != measured.model.basis or learned.convention != measured.model.convention:
        raise ModelFileError(f"{where}: basis/convention {learned.basis}/{learned.convention} "
                             f"differ from the measured fit's {measured.model.basis}/"
                             f"{measured.model.convention}")
    if tuple(learned.sensor_shape) != tuple(measured.sensor_shape):
        raise ModelFileError(f"{where}: sensor {list(learned.sensor_shape)} differs from the "
                             f"comparison grid {list(measured.sensor_shape)}")
    kernels = pad_kernels(learned.kernels, tuple(measured.sensor_shape))
    if kernels.shape[1] != measured.model.kernels.shape[1]:
        raise ModelFileError(f"{where}: {kernels.shape[1]} channel(s) but the grid has "
                             f"{measured.model.kernels.shape[1]}")
    shift = (0.0, 0.0)
    if options.align:
        shift = register_shift(luminance(measured.model.kernels[0]), luminance(kernels[0]))
        if abs(shift[0]) > 0.005 or abs(shift[1]) > 0.005:
            kernels = shift_image(kernels.reshape(-1, *kernels.shape[-2:]), shift)[0].reshape(
                kernels.shape)
    return kernels, (float(shift[0]), float(shift[1]))


def _angles(kernels: np.ndarray, measured: MeasuredModes, n_pca: int
            ) -> tuple[np.ndarray, np.ndarray | None]:
    eigen = principal_angles_deg(kernels, measured.model.kernels)
    if measured.pca_components is None or measured.pca_region is None:
        return eigen, None
    n = min(n_pca or len(kernels), len(measured.pca_components))
    region = measured.pca_region
    working = resample(kernels, region.shape)
    pca = principal_angles_deg(working[:, :, region], measured.pca_components[:n][:, :, region])
    return eigen, pca


def _measured_maps(modes: MeasuredModes, options: CompareOptions
                   ) -> tuple[np.ndarray, np.ndarray, dict[str, DisplacementMap]]:
    """The measured kernels' ``(K, H, W)`` luminance, caustic mask and displacement maps."""
    lum = np.stack([luminance(k) for k in modes.model.kernels])
    mask = comparison_mask(lum[0], options)
    return lum, mask, _kernel_displacements(lum, modes.model.kernel_names, mask, options)


def compare_model(model: KernelModel, measured: MeasuredModes, label: str = "learned",
                  options: CompareOptions | None = None, where: str = "learned kernels",
                  maps: tuple[np.ndarray, np.ndarray, dict[str, DisplacementMap]] | None = None
                  ) -> KernelSetComparison:
    """Compare one kernel model with measured modes (see the module docstring); ``maps``: the
    measured side's :func:`_measured_maps` when already computed.

    Raises
    ------
    ModelFileError
        Basis, convention, sensor size or channels differ from the measured fit's.
    """
    options = options or CompareOptions()
    kernels, shift = _prepare_learned(model, measured, options, where)
    names = measured.model.kernel_names
    lum = np.stack([luminance(k) for k in kernels])
    meas_lum, mask, meas_disp = maps or _measured_maps(measured, options)
    disp = _kernel_displacements(lum, names, mask, options)
    metrics = {}
    for k, name in enumerate(names[1:], 1):
        warp = measured.warps.get(name)
        metrics[name] = {
            "vs_measured_kernels": map_agreement(disp[name], meas_disp[name],
                                                 options.min_displacement_px),
            "vs_measured_warp": None if warp is None else map_agreement(
                disp[name], warp, options.min_displacement_px),
            "difference_ncc": normalized_correlation(lum[k] - lum[0], meas_lum[k] - meas_lum[0]),
        }
    eigen, pca = _angles(kernels, measured, options.n_pca)
    return KernelSetComparison(label=label, kernels=kernels, displacements=disp,
                               metrics=metrics, angles_eigen_deg=eigen, angles_pca_deg=pca,
                               global_shift_px=shift)


def _as_model(value: KernelModel | str | os.PathLike, label: str) -> tuple[KernelModel, str]:
    """A kernel model, and what messages call it (its file, or ``label``)."""
    if isinstance(value, KernelModel):
        return value, label
    return load_kernels(value), str(value)


def check_learned(model: KernelModel, where: str) -> None:
    """Refuse a kernel model without correction kernels (nothing to compare)."""
    if len(model.kernels) < 2:
        raise ModelFileError(f"{where}: basis {model.basis!r} has a single kernel; the "
                             "comparison needs Kbase and correction kernels (e.g. basis "
                             "'paper': Kbase, Kv, Kh)")


def compare_kernels(learned: KernelModel | str | os.PathLike,
                    measured: PsfGrid | KernelModel | str | os.PathLike | MeasuredModes,
                    initial: KernelModel | str | os.PathLike | None = None,
                    options: CompareOptions | None = None, progress: bool = False
                    ) -> KernelComparison:
    """Compare learned eigen-kernels with the measured modes of the same camera.

    Parameters
    ----------
    learned : KernelModel or path
        The trained kernels (at least two).
    measured : PsfGrid, path, KernelModel or MeasuredModes
        The camera's PSF grid, another kernel file (``.npz`` or model: no warps or PCA modes),
        or modes from :func:`measure_modes` on the learned sensor grid (reused across models).
    initial : KernelModel or path, optional
        The kernels before training, reported the same way.
    progress : bool
        Progress bar for the grid fit.

    Raises
    ------
    ModelFileError
        A kernel file is unreadable, has one kernel, or its basis, convention or sensor size
        differs from the other's.
    GridFormatError, InvalidInputError
        Not a grid, or PSFs that cannot be brought to the kernel file's sensor size.
    """
    options = options or CompareOptions()
    learned_model, where = _as_model(learned, "learned kernels")
    check_learned(learned_model, where)
    initial_model = None
    if initial is not None:
        initial_model, iw = _as_model(initial, "initial kernels")
        check_learned(initial_model, iw)
        for attr in ("basis", "convention", "sensor_shape"):
            if getattr(initial_model, attr) != getattr(learned_model, attr):
                raise ModelFileError(f"{iw}: {attr} {getattr(initial_model, attr)!r} differs "
                                     f"from the learned file's {getattr(learned_model, attr)!r}")
    if isinstance(measured, MeasuredModes):
        modes = measured
    elif isinstance(measured, KernelModel) or (isinstance(measured, (str, os.PathLike))
                                               and Path(measured).suffix == ".npz"):
        # another kernel file as the measured side (a grid fit, a pairs fit, an oracle)
        modes = modes_from_kernel_file(*_as_model(measured, "measured kernels"),
                                       learned_model.basis, learned_model.convention,
                                       tuple(learned_model.sensor_shape))
    else:
        modes = measure_modes(measured, learned_model.basis, learned_model.convention,
                              tuple(learned_model.sensor_shape), options, progress)
    maps = _measured_maps(modes, options)
    _, mask, meas_disp = maps
    result_learned = compare_model(learned_model, modes, "learned", options, where, maps)
    result_initial = None if initial_model is None else compare_model(
        initial_model, modes, "initial", options, "initial kernels", maps)
    vs_warp = {name: map_agreement(meas_disp[name], warp, options.min_displacement_px)
               for name, warp in modes.warps.items() if name in meas_disp}
    notes = list(modes.notes)
    if learned_model.kernels.shape[-2:] != tuple(learned_model.sensor_shape):
        notes.append(f"learned kernels {learned_model.kernels.shape[-2]}x"
                     f"{learned_model.kernels.shape[-1]} zero-padded to the sensor size")
    return KernelComparison(learned=result_learned, initial=result_initial, measured=modes,
                            measured_displacements=meas_disp, measured_kernels_vs_warp=vs_warp,
                            mask=mask, options=options, notes=notes,
                            kernel_change=kernel_change_report(
                                result_learned, result_initial, modes, options))


def kernel_change_report(learned: KernelSetComparison, initial: KernelSetComparison | None,
                         modes: MeasuredModes, options: CompareOptions) -> dict:
    """:func:`~research.compare.kernel_change.split_kernel_changes` of the learned kernels vs the
    measured (and initial) ones on the measured kernels' dilated caustic support."""
    names = modes.model.kernel_names
    support = caustic_support(modes.model.kernels, options.mask_level, options.mask_dilate)
    out: dict = {"support_pixels": int(support.sum()),
                 "learned_vs_measured": split_kernel_changes(
                     learned.kernels, modes.model.kernels, support, names, options.flow_method)}
    if initial is not None:
        out["learned_vs_initial"] = split_kernel_changes(
            learned.kernels, initial.kernels, support, names, options.flow_method)
    return out
