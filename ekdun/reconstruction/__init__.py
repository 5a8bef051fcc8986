"""Reconstruction: trained checkpoints and classical ADMM-TV.

:mod:`ekdun.reconstruction.tv_admm_steps` holds the ADMM-TV updates shared with Le-ADMM-U
(:mod:`ekdun.models.le_admm_u` imports it, so this package must not import the models or the
training code when it loads: :func:`reconstruct_files` is loaded on first use).
"""

from __future__ import annotations

from typing import Any

from ekdun.reconstruction.admm_tv import admm_tv

__all__ = ["admm_tv", "reconstruct_files"]


def __getattr__(name: str) -> Any:
    # PEP 562: reconstruct.py needs the models (via training.builder); loading it lazily
    # keeps models -> reconstruction.tv_admm_steps free of an import circle.
    if name == "reconstruct_files":
        from ekdun.reconstruction.reconstruct import reconstruct_files

        return reconstruct_files
    raise AttributeError(f"module 'ekdun.reconstruction' has no attribute {name!r}")
