"""Every random generator's state, stored in a training checkpoint so that ``--resume``
continues exactly: torch (CPU and CUDA), numpy's global MT19937 and Python's ``random``."""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch


def rng_state() -> dict[str, Any]:
    """Every RNG state as tensors/ints (``weights_only``-loadable)."""
    _kind, keys, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002 (global state)
    version, internal, gauss = random.getstate()
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy_keys": torch.as_tensor(np.asarray(keys, dtype=np.int64)),
        "numpy_pos": int(pos), "numpy_has_gauss": int(has_gauss),
        "numpy_cached": float(cached),
        "python_version": int(version),
        "python_internal": torch.as_tensor(internal, dtype=torch.int64),
        "python_gauss": None if gauss is None else float(gauss),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Inverse of :func:`rng_state` (the tensors may live on any device)."""
    torch.set_rng_state(state["torch"].cpu())
    keys = state["numpy_keys"].cpu().numpy().astype(np.uint32)
    numpy_state = ("MT19937", keys, int(state["numpy_pos"]), int(state["numpy_has_gauss"]),
                   float(state["numpy_cached"]))
    np.random.set_state(numpy_state)  # noqa: NPY002 (global state)
    internal = tuple(int(v) for v in state["python_internal"].cpu().tolist())
    random.setstate((int(state["python_version"]), internal, state["python_gauss"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])
