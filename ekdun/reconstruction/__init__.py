"""Reconstruction: trained checkpoints, and the one ADMM-TV for kernel files and PSF images."""

from ekdun.reconstruction.admm import solve_tv
from ekdun.reconstruction.classical import (
    ClassicalOptions,
    ModelReconstructor,
    admm_tv,
    reconstruct_folder,
    reconstruct_with_model,
)
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from ekdun.reconstruction.reconstruct import reconstruct_files

__all__ = ["ClassicalOptions", "ExtendedSceneOperator", "ModelReconstructor", "admm_tv",
           "reconstruct_files", "reconstruct_folder", "reconstruct_with_model", "solve_tv"]
