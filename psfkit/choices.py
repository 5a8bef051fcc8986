"""Names that options choose from (methods, weight bases), kept apart from the modules that
implement them so that ``psfkit --help`` starts fast; each list is written once."""

from __future__ import annotations

#: Dense-flow methods of :func:`psfkit.calibration.warp.dense_flow`.
FLOW_METHODS = ("dis", "farneback", "ilk", "tvl1")

#: Weight bases compared by cross-validation in :func:`psfkit.fitting.grid.fit.fit_eigen_grid` by
#: default (with the fitted basis), and the full list behind ``--cv-bases all``.
CV_BASES = ("si", "paper")
CV_BASES_ALL = ("si", "paper", "paper+odd", "paper+cross", "paper+odd+cross", "poly:2")

#: Where :func:`psfkit.fitting.grid.fit.fit_eigen_grid` places each PSF (``psfkit fit-eigen
# --shifts``):
#: at the affine field-to-shift map's shift (default) or at its own registered shift.
SHIFT_MODES = ("affine", "registered")
