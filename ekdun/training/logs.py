"""Training logs a user can plot: ``log.csv`` (one row per epoch), rewritten atomically."""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path
from typing import Any

from psfkit.io.atomic import atomic_file

COLUMNS = ("epoch", "train_loss", "lr", "seconds", "images_per_second")
#: written after :data:`COLUMNS` when a row has it (training with an extra loss)
OPTIONAL_COLUMNS = ("extra_loss",)


def write_csv_log(path: str | os.PathLike, history: list[dict[str, Any]]) -> Path:
    """Write the per-epoch ``history`` as CSV (columns :data:`COLUMNS`, then those of
    :data:`OPTIONAL_COLUMNS` that any row has)."""
    buffer = io.StringIO()
    extra = tuple(c for c in OPTIONAL_COLUMNS if any(c in row for row in history))
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS + extra, extrasaction="ignore")
    writer.writeheader()
    for row in history:
        writer.writerow(row)
    path = Path(path)
    with atomic_file(path) as tmp:
        tmp.write_text(buffer.getvalue(), encoding="utf-8")
    return path
