"""The names that ekdun's options choose from, in a module free of torch (for the parser)."""

from __future__ import annotations

#: ``--network`` values and :func:`ekdun.nets.factory.build_model` names.
MODEL_NAMES: tuple[str, ...] = ("ekdun", "le-admm-u", "updn")
#: ``--amp`` values (:func:`ekdun.device.resolve_amp`).
AMP_CHOICES: tuple[str, ...] = ("auto", "off", "bf16", "fp16")
