"""Base class of unrolled reconstruction networks: ``prepare`` (per forward pass),
``initial_state``, ``update`` per iteration and ``output`` (the LenslessPiCam pattern). The
loop is plain Python over a fixed count, so ``torch.export`` unrolls it into a static graph.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from ekdun.errors import ConfigurationError
from psfkit.forward.kernelfile import KernelModel

State = dict[str, Tensor]


def count_parameters(module: nn.Module, trainable_only: bool = True) -> int:
    """Number of (trainable) scalar parameters of ``module``; buffers are not counted."""
    return sum(p.numel() for p in module.parameters()
               if p.requires_grad or not trainable_only)


class UnrolledNetwork(nn.Module):
    """An unrolled iterative reconstruction ``y (B, C, H', W') → x̂ (B, C, H', W')``.

    Attributes
    ----------
    physics : nn.Module
        The forward operator.
    config : dataclass
        The network's configuration; ``config.iterations`` unrolled iterations.
    seed_kernels : KernelModel or None
        The kernel model the network was built from (:meth:`set_seed_kernels`); ``None`` for
        a network built directly. Training writes it as ``kernels_initial.npz``.
    """

    seed_kernels: KernelModel | None

    def __init__(self, physics: nn.Module, config: Any) -> None:
        super().__init__()
        if config.iterations < 1:
            raise ConfigurationError(f"iterations must be >= 1, got {config.iterations}")
        self.iterations = int(config.iterations)
        self.seed_kernels = None
        self.config = config
        self.physics = physics

    def per_iteration(self, value: float, dtype: torch.dtype) -> nn.Parameter:
        """A learned scalar per iteration ``(iterations,)``, each starting at ``value``."""
        return nn.Parameter(torch.full((self.iterations,), value, dtype=dtype))

    def set_seed_kernels(self, seed: KernelModel) -> None:
        """Remember the kernel model the network was built from (validated first:
        :class:`~psfkit.errors.ModelFileError`)."""
        seed.validate(where="seed kernels")
        self.seed_kernels = seed

    def prepare(self, y: Tensor) -> dict[str, Any]:
        """Per-forward-pass quantities shared by all iterations (checks ``y``)."""
        raise NotImplementedError

    def initial_state(self, y: Tensor, context: dict[str, Any]) -> State:
        """Iteration-0 variables."""
        raise NotImplementedError

    def update(self, i: int, state: State, context: dict[str, Any]) -> State:
        """Iteration ``i`` (0-based)."""
        raise NotImplementedError

    def output(self, state: State, context: dict[str, Any]) -> Tensor:
        """The reconstruction from the final state."""
        raise NotImplementedError

    def iterate(self, y: Tensor) -> tuple[State, dict[str, Any]]:
        """Run all iterations; returns the final state and the context."""
        context = self.prepare(y)
        state = self.initial_state(y, context)
        for i in range(self.iterations):
            state = self.update(i, state, context)
        return state, context

    def forward(self, y: Tensor) -> Tensor:
        """Reconstruct the scene from the measurement ``y`` ``(B, C, H', W')``."""
        state, context = self.iterate(y)
        return self.output(state, context)

    def parameter_count(self) -> int:
        """Trainable scalar parameters (fixed PSFs are buffers and not counted)."""
        return count_parameters(self)

    def parameter_breakdown(self) -> dict[str, int]:
        """Trainable parameters per top-level component (``physics``, ``priors``, ...)."""
        counts: dict[str, int] = {}
        for name, p in self.named_parameters():
            if p.requires_grad:
                key = name.split(".")[0]
                counts[key] = counts.get(key, 0) + p.numel()
        return counts
