"""Research studies of the ekdun toolkit: oracles, identifiability, estimator-vs-oracle
comparisons, kernel parameterisations, U-Net absorption, consistency descent, tolerance and
significance calibrations (README.md says what each answers and how to run it).

Not installed (``pip install`` ships ``psfkit`` and ``ekdun`` only) and never imported by them
(an import-linter contract in pyproject.toml): run the studies from a source checkout, at the
repository root, as ``python -m research.<name>``. Research may import the product.
"""
