"""The names of the reconstruction networks, in one place.

A module of its own, free of torch, so that the ``ekdun`` command-line parser can offer them
without importing torch (:mod:`ekdun.nets` imports it).
"""

from __future__ import annotations

#: ``--model`` values and :func:`ekdun.nets.factory.build_model` names.
MODEL_NAMES: tuple[str, ...] = ("ekdun", "le-admm-u", "updn")
