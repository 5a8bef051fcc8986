"""Reconstruction: trained checkpoints, classical ADMM-TV, and TV solvers for kernel files."""

from ekdun.reconstruction.admm_tv import admm_tv
from ekdun.reconstruction.classical import (
    ClassicalOptions,
    ModelReconstructor,
    reconstruct_folder,
    reconstruct_with_model,
)
from ekdun.reconstruction.ek_admm import ek_admm_tv
from ekdun.reconstruction.extended_scene import ExtendedSceneOperator
from ekdun.reconstruction.pdhg_tv import pdhg_tv
from ekdun.reconstruction.reconstruct import reconstruct_files
from ekdun.reconstruction.source_admm import source_admm_tv

__all__ = ["ClassicalOptions", "ExtendedSceneOperator", "ModelReconstructor", "admm_tv",
           "ek_admm_tv", "pdhg_tv", "reconstruct_files", "reconstruct_folder",
           "reconstruct_with_model", "source_admm_tv"]
