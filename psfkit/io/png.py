"""PNG files: the size declared in the header, and OpenCV's decoding without its C-level
messages on stderr (used by :func:`psfkit.io.images.read_image`)."""

from __future__ import annotations

import contextlib
import os
import struct
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import numpy as np

from psfkit.errors import InvalidInputError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}   # IHDR colour type -> decoded channels


def png_declared_shape(path: Path) -> tuple[int, int, int]:
    """``(height, width, channels)`` from a PNG's IHDR chunk (the first 33 bytes)."""
    with open(path, "rb") as fh:
        head = fh.read(33)
    if len(head) < 33 or not head.startswith(_PNG_SIGNATURE) or head[12:16] != b"IHDR":
        raise InvalidInputError(f"{path}: not a readable image (no PNG header)")
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16):
        raise InvalidInputError(f"{path}: not a readable image (PNG colour type {colour}, "
                                f"bit depth {depth})")
    return height, width, _PNG_CHANNELS[colour]


class _NativeStderr:
    """File descriptor 2 redirected to a temporary file while at least one thread decodes
    (nested and concurrent uses share one redirection)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.users = 0
        self.saved = -1
        self.log: IO[bytes] | None = None

    @contextlib.contextmanager
    def captured(self) -> Iterator[IO[bytes]]:
        with self.lock:
            if self.users == 0:
                self.log = tempfile.TemporaryFile()
                self.saved = os.dup(2)
                os.dup2(self.log.fileno(), 2)
            self.users += 1
            log = self.log
        assert log is not None
        try:
            yield log
        finally:
            with self.lock:
                self.users -= 1
                if self.users == 0:
                    os.dup2(self.saved, 2)
                    os.close(self.saved)
                    log.close()


_NATIVE_STDERR = _NativeStderr()


def decode_png(path: Path) -> np.ndarray:
    """OpenCV's decoding of a PNG whose declared size was checked.

    What OpenCV and libpng print from C (``libpng warning: iCCP ...``) goes to a temporary
    file instead of the command's stderr; its first line explains a decoding failure.
    """
    import cv2

    with contextlib.suppress(Exception):   # OpenCV's own log is ours to report, not to print
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    with _NATIVE_STDERR.captured() as log:
        position = log.tell()
        array = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        log.seek(position)
        said = log.read(2000).decode("utf-8", "replace").strip().splitlines()
        log.seek(0, os.SEEK_END)
    if array is None:
        raise ValueError(said[0] if said else "OpenCV could not decode it")
    return array
