"""Names of the methods and weight bases that options choose from, without the modules that
implement them.

The command-line parsers list these as choices and defaults; keeping them here (no scipy, no
OpenCV, no torch) lets ``psfkit --help`` start in a fraction of a second. The implementing
modules import them from here, so each list is written once.
"""

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
