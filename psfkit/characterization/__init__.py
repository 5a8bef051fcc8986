"""Characterization of a PSF grid: one pass over it (registration, gain, MAE, warp, the
verdict) and what it holds."""
