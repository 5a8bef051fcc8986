"""The result of a pairs fit (:class:`PairFit`): kernels, per-pair scales, training errors
and the solver's history, with the regularisation and constraints the kernel file records.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from psfkit.fitting.pairs.constraints import kernel_summary
from psfkit.fitting.pairs.options import PairFitOptions
from psfkit.fitting.pairs.regularisation import RegularisationChoice
from psfkit.forward.kernelfile import KernelModel
from psfkit.io.read_options import ReadOptions


@dataclass
class PairFit:
    """Result of :func:`psfkit.fitting.pairs.fit.fit_pairs`: kernels ``(K, C, Hk, Wk)``, per-pair
    scales and relative training errors, and the solver's history."""

    kernels: np.ndarray = field(repr=False)
    basis: str
    convention: str
    scales: np.ndarray
    training_error: np.ndarray
    history: list[dict[str, Any]]
    options: PairFitOptions
    support: np.ndarray | None = field(default=None, repr=False)
    #: The relative weights solved with (``{"tikhonov", "difference"}``: the given ones and
    #: those chosen by held-out error).
    weights: dict[str, float] = field(default_factory=dict)
    #: How each automatic weight was chosen
    # (:class:`~psfkit.fitting.pairs.regularisation.RegularisationChoice`).
    regularisation: list[RegularisationChoice] = field(default_factory=list)
    #: How ``convention="auto"`` chose the convention
    #: (:func:`~psfkit.fitting.pairs.regularisation.convention_record`), or ``None``.
    convention_choice: dict[str, Any] | None = None

    def regularisation_record(self) -> dict[str, Any]:
        """The regularisation record (kernel file, fit report): the weights used and each automatic
        choice's held-out path."""
        automatic = {c.parameter: c.as_dict() for c in self.regularisation}
        return {"weights": dict(self.weights),
                "chosen_by": {p: ("held-out error" if p in automatic else "given")
                              for p in self.weights},
                "automatic": automatic}

    def physics(self) -> dict[str, Any]:
        """The constraints imposed and the kernels' energies ``[K][C]``, support fraction, negative
        and non-finite pixel counts."""
        o = self.options
        return {"constraints": {"nonneg": o.nonneg, "support": o.support},
                **kernel_summary(self.kernels)}

    def kernel_model(self, provenance: dict[str, Any] | None = None,
                     read_options: ReadOptions | None = None) -> KernelModel:
        """The kernel file content; ``read_options``: how the fitted pairs were read."""
        channels = ("L",) if self.kernels.shape[1] == 1 else ("R", "G", "B")
        provenance = {**(provenance or {}), "regularisation": self.regularisation_record(),
                      **({"convention_choice": self.convention_choice}
                         if self.convention_choice else {})}
        return KernelModel(kernels=self.kernels, basis=self.basis, convention=self.convention,
                           sensor_shape=self.kernels.shape[-2:], channels=channels,
                           scene_padding=self.options.scene_padding,
                           normalization="fitted in the pairs' own units: y = A x",
                           provenance=provenance, read_options=read_options)
