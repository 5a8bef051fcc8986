"""Training: loop, checkpoints, logs, distributed helpers and kernel export."""

from ekdun.errors import CheckpointError
from ekdun.nets.checkpoint import load_checkpoint, save_checkpoint
from ekdun.nets.export import export_kernels, initial_kernels
from ekdun.training.trainer import TrainOptions, train

__all__ = ["CheckpointError", "TrainOptions", "export_kernels", "initial_kernels",
           "load_checkpoint", "save_checkpoint", "train"]
