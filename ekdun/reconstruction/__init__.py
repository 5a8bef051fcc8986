"""Reconstruction: trained checkpoints and classical ADMM-TV."""

from ekdun.reconstruction.admm_tv import admm_tv
from ekdun.reconstruction.reconstruct import reconstruct_files

__all__ = ["admm_tv", "reconstruct_files"]
