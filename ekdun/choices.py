"""The names that ekdun's options choose from (networks, autocast precisions), in one place.

A module of its own, free of torch, so that the ``ekdun`` command-line parser can offer them
without importing torch (:mod:`ekdun.nets` and :mod:`ekdun.device` import it).
"""

from __future__ import annotations

#: ``--network`` values and :func:`ekdun.nets.factory.build_model` names.
MODEL_NAMES: tuple[str, ...] = ("ekdun", "le-admm-u", "updn")
#: ``--amp`` values (:func:`ekdun.device.resolve_amp`).
AMP_CHOICES: tuple[str, ...] = ("auto", "off", "bf16", "fp16")
