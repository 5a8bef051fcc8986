"""Export the learned kernels of an EK-DUN as a psfkit kernel file (hand-off to psfkit)."""

from __future__ import annotations

import os
from dataclasses import replace
from typing import Any

import numpy as np
from torch import nn

from ekdun.data.pairs import recorded_read_options
from ekdun.errors import CheckpointError, ConfigurationError
from ekdun.nets.builder import network_from_checkpoint
from ekdun.nets.checkpoint import load_checkpoint
from psfkit.errors import ModelFileError
from psfkit.forward.kernelfile import KernelModel


def export_kernels(model_or_checkpoint: nn.Module | str | os.PathLike | dict[str, Any]
                   ) -> KernelModel:
    """The learned kernels of an EK-DUN as a :class:`KernelModel` with the seed model's
    basis and geometry, and a ``provenance`` saying where they came from.

    Parameters
    ----------
    model_or_checkpoint : EKDUN, checkpoint path or loaded checkpoint dict
        A network from :func:`ekdun.nets.builder.build_network`, or a training checkpoint.

    Raises
    ------
    ConfigurationError
        The network has no eigen-kernel physics (Le-ADMM-U, UPDN).
    """
    where = "" if isinstance(model_or_checkpoint, (nn.Module, dict)) \
        else f"{model_or_checkpoint}: "            # the message names the checkpoint file
    if isinstance(model_or_checkpoint, nn.Module):
        model = model_or_checkpoint
        model = getattr(model, "module", model)         # unwrap DistributedDataParallel
        epoch, data = None, None
    else:
        model, doc = network_from_checkpoint(model_or_checkpoint)
        epoch, data = doc["metadata"].get("epoch"), doc["metadata"].get("data")
    from ekdun.nets.ekdun_net import EKDUN

    if not isinstance(model, EKDUN):
        raise ConfigurationError(f"{where}only EK-DUN has eigen kernels to export, not "
                                 f"{type(model).__name__}")
    seed = model.seed_kernels
    kernels = model.current_kernels().detach().cpu().numpy().astype(np.float32)
    if seed is None:
        # A network built directly (not by build_network): its physics has the geometry.
        n = kernels.shape[0]
        seed = KernelModel(kernels=kernels, basis="paper" if n == 3 else "si",
                           convention=model.physics.convention,
                           sensor_shape=tuple(model.physics.sensor_shape),
                           channels=("R", "G", "B") if kernels.shape[1] == 3 else ("L",),
                           scene_padding=model.physics.scene_padding, normalization="unknown")
    provenance = {"source": "ekdun training (learned kernels)", "epoch": epoch,
                  "kernel_param": getattr(model.kernel_param, "name", "free"),
                  "seed_provenance": seed.provenance}
    if isinstance(data, dict) and isinstance(data.get("names"), list) and data.get("root"):
        # the pairs the kernels were trained on, as fit-pairs records its own: psfkit
        # eval-model marks them "fitted" and the held-out ones apart
        provenance.update(pairs=str(data["root"]), names=list(data["names"]),
                          holdout=list(data.get("holdout") or []))
    # learned on the training pairs: their read options are the model's (else the seed's)
    read_options = recorded_read_options(data, where.rstrip(": ") or "checkpoint") \
        if isinstance(data, dict) and data else seed.read_options
    return replace(seed, kernels=kernels, provenance=provenance, read_options=read_options,
                   normalization=f"learned (initialised from: {seed.normalization})")


def initial_kernels(checkpoint: str | os.PathLike | dict[str, Any]) -> KernelModel:
    """The seed kernels an EK-DUN checkpoint (path or loaded dict) was trained from, as
    ``kernels_initial.npz`` holds them.

    Raises
    ------
    CheckpointError
        Not a readable ekdun checkpoint.
    ConfigurationError
        The network has no eigen-kernel physics (Le-ADMM-U, UPDN).
    """
    doc = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint)
    where = "checkpoint" if isinstance(checkpoint, dict) else str(checkpoint)
    try:
        meta = doc["metadata"]
        if meta["model"] != "ekdun":
            raise ConfigurationError(f"{where}: only EK-DUN has eigen kernels to export, not "
                                     f"{meta['model']}")
        return KernelModel.from_metadata(doc["initial_kernels"].numpy(),
                                         meta["kernel_metadata"], where="initial kernels")
    except (KeyError, TypeError, ValueError, AttributeError, ModelFileError) as exc:
        raise CheckpointError(f"{where}: no initial kernels ({exc})") from None
