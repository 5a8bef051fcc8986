"""Calibration of a measured PSF grid: preprocessing, registration, alignment, gain,
MAE, warps and where a PSF is on its frame."""
