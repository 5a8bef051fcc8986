"""Eigen-kernel fits of a measured PSF grid (``psfkit fit-eigen``)."""
