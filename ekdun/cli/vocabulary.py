"""ekdun's flag vocabulary: psfkit's (:data:`psfkit.cli.vocabulary.VOCABULARY`), with what the
shared flags mean in ekdun's commands, and ekdun's own flags; :func:`add_flag` adds them with
ekdun's numeric ranges.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

from ekdun.choices import AMP_CHOICES, MODEL_NAMES
from ekdun.flag_ranges import device_name, flag
from psfkit.cli import vocabulary as shared
from psfkit.cli.vocabulary import SharedFlag

_THREADS = shared.VOCABULARY["--threads"]
_HOLDOUT = shared.VOCABULARY["--holdout"]

#: Every flag of the vocabulary, as ekdun's commands use it.
VOCABULARY: dict[str, SharedFlag] = {**shared.VOCABULARY, **{f.name: f for f in (
    replace(_THREADS, default_text="2 (psfkit report), torch's default (ekdun), the CPUs up to "
                                   "16 and one per 64 scenes (make-dataset)",
            per_command={**_THREADS.per_command,
                         "make-dataset": {"meaning": "processes drawing the scenes at the same "
                                                     "time",
                                          "default_text": "the CPUs up to 16 and one per 64 "
                                                          "scenes"},
                         **{cmd: {"meaning": "torch's CPU threads (intra-op)",
                                  "default_text": "torch's default"}
                            for cmd in ("train", "eval", "reconstruct", "admm")}}),
    replace(_HOLDOUT, meaning="pairs (file stems, e.g. im65; comma-separated, repeatable) left "
                              "out of the fit or of training; eval-model: the pairs the model "
                              "was not fitted on, where its file does not record them",
            per_command={**_HOLDOUT.per_command,
                         "train": {"meaning": "pairs (file stems, e.g. im65; comma-separated, "
                                              "repeatable) left out of training"}}),
    SharedFlag("--network", "network", "reconstruction network: ekdun, le-admm-u or updn",
               "ekdun", default="ekdun", choices=MODEL_NAMES),
    SharedFlag("--loader-workers", "loader_workers",
               "DataLoader worker processes when the dataset does not fit on the device",
               "2", default=2, kind="number", metavar="N"),
    SharedFlag("--device", "device", "torch device: auto (cuda if present, else cpu), cpu, "
               "cuda, cuda:N or mps", "auto", default="auto", parse=device_name),
    SharedFlag("--amp", "amp", "autocast precision of the network (the physics FFTs stay "
               "float32): auto = fp16 on CUDA, off on CPU; bf16 also works on CPU; fp16 "
               "needs CUDA", "auto", default="auto", choices=AMP_CHOICES),
    SharedFlag("--tv", "tv", "TV weight relative to the measurement's peak and the operator "
               "norm ||A|| (power iteration, crop included): the same objective for every "
               "model and solver", "3e-4", kind="number"),
)}}

#: Deprecated spellings of ekdun's commands (same shape as psfkit's).
DEPRECATED: dict[tuple[str, str], str] = {
    ("train", "--model"): "--network",
    ("train", "--workers"): "--loader-workers",
    ("admm", "--tau"): "--tv",
}


def add_flag(parser: argparse.ArgumentParser | argparse._ArgumentGroup, name: str,
             command: str, note: str = "", **extra: Any) -> argparse.Action:
    """:func:`psfkit.cli.vocabulary.add_flag` with ekdun's vocabulary, deprecated spellings
    and numeric ranges."""
    return shared.add_flag(parser, name, command, note, vocabulary=VOCABULARY,
                           deprecated=DEPRECATED, number_type=flag, **extra)


def set_threads(args: argparse.Namespace) -> None:
    """``--threads``: torch's intra-op threads (left alone when not given)."""
    import torch

    if getattr(args, "threads", None):
        torch.set_num_threads(args.threads)
