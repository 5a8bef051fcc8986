"""Plain-JSON conversion of nested results, and JSON outputs written atomically."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.io.atomic import atomic_file


def jsonable(value: Any) -> Any:
    """Plain-JSON version of nested results (NaN/Inf → null, numpy → Python)."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_json(path: str | os.PathLike, doc: Any, indent: int = 1) -> Path:
    """Write ``jsonable(doc)`` (NaN/Inf as ``null``) to ``path`` atomically, replacing it;
    returns ``path``."""
    path = Path(path)
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(jsonable(doc), indent=indent) + "\n", encoding="utf-8")
    return path
