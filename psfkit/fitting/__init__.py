"""Model fits: eigen-kernels from a PSF grid (:mod:`psfkit.fitting.grid`) or from (scene,
measurement) pairs (:mod:`psfkit.fitting.pairs`), and the verdict that chooses a model."""
