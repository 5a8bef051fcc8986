"""JSON documents from outside, read strictly, and JSON outputs that are always finite."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from psfkit.errors import InvalidInputError
from psfkit.io.validation import MAX_JSON_BYTES, MAX_JSON_DEPTH


def _nesting_depth(text: str) -> int:
    """Deepest bracket nesting outside strings (cheap, linear, no recursion)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def load_json_document(text: str | bytes, where: str) -> Any:
    """Parse JSON from outside strictly: duplicate keys, ``NaN``/``Infinity``, numbers that
    overflow (``1e400``) and nesting deeper than ``MAX_JSON_DEPTH`` raise
    :class:`InvalidInputError` naming ``where``."""
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise InvalidInputError(f"{where}: not a UTF-8 text file") from None
    if _nesting_depth(text) > MAX_JSON_DEPTH:
        raise InvalidInputError(f"{where}: JSON nested deeper than {MAX_JSON_DEPTH} levels")

    def refuse_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        doc: dict[str, Any] = {}
        for key, value in pairs:
            if key in doc:
                raise InvalidInputError(f"{where}: key {key!r} appears twice")
            doc[key] = value
        return doc

    def refuse_constant(name: str) -> float:
        raise InvalidInputError(f"{where}: {name} is not a valid JSON number")

    def refuse_overflow(number: str) -> float:
        value = float(number)
        if not math.isfinite(value):
            raise InvalidInputError(f"{where}: number {number} is out of range")
        return value

    try:
        return json.loads(text, object_pairs_hook=refuse_duplicates,
                          parse_constant=refuse_constant, parse_float=refuse_overflow)
    except json.JSONDecodeError as exc:
        raise InvalidInputError(f"{where}: invalid JSON at line {exc.lineno}: {exc.msg}") \
            from None
    except RecursionError:
        raise InvalidInputError(f"{where}: JSON nested too deeply") from None


def read_json_file(path: str | os.PathLike, where: str | None = None,
                   max_bytes: int = MAX_JSON_BYTES) -> Any:
    """:func:`load_json_document` of a file, refused first when missing or larger than
    ``max_bytes``; ``where`` (default: the path) names it."""
    path = Path(path)
    where = where or str(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise InvalidInputError(f"{where}: no such file") from None
    if size > max_bytes:
        raise InvalidInputError(f"{where}: {size} bytes is larger than the {max_bytes} bytes a "
                                "JSON document of this toolkit may have")
    with open(path, "rb") as fh:
        return load_json_document(fh.read(max_bytes + 1), where)


def dumps_finite(doc: Any, what: str, **kwargs: Any) -> str:
    """``json.dumps(doc, allow_nan=False, **kwargs)``; a NaN/Inf raises
    :class:`InvalidInputError` naming the output ``what`` and the key."""
    try:
        return json.dumps(doc, allow_nan=False, **kwargs)
    except ValueError:
        pass
    where = _first_non_finite(doc, kwargs.get("default"))
    raise InvalidInputError(f"{what}: refusing to write a non-finite number (NaN/Inf)"
                            + (f" at {where}" if where else "")
                            + "; an input or a parameter made the result diverge")


def _first_non_finite(value: Any, default: Any, path: str = "") -> str | None:
    if isinstance(value, dict):
        items = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        if not isinstance(value, (int, float, str, bool, type(None))) and default is not None:
            try:
                value = default(value)
            except Exception:
                return None
        if isinstance(value, float) and not math.isfinite(value):
            return path or "top level"
        return None
    for key, item in items:
        found = _first_non_finite(item, default, f"{path}.{key}" if path else str(key))
        if found:
            return found
    return None
