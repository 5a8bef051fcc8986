"""Training logs a user can plot: ``log.csv`` (one row per epoch), rewritten atomically."""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path
from typing import Any

from psfkit.io.atomic import atomic_file

COLUMNS = ("epoch", "train_loss", "lr", "seconds", "images_per_second")


def write_csv_log(path: str | os.PathLike, history: list[dict[str, Any]]) -> Path:
    """Write the per-epoch ``history`` as CSV (columns :data:`COLUMNS`)."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for row in history:
        writer.writerow(row)
    path = Path(path)
    with atomic_file(path) as tmp:
        tmp.write_text(buffer.getvalue(), encoding="utf-8")
    return path
