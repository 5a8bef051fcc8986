"""Numerical helpers shared by the domains: binning, windows, a bounded parallel map, and
uncertainties with significance tests."""
