"""ekdun: eigen-kernel forward models and unrolled reconstruction networks (PyTorch)."""

__version__ = "0.1.0"
