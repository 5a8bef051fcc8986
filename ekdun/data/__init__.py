"""Datasets: pairs folders, dead-leaves scenes and the cached virtual-bench dataset."""
