"""The read options (channel order, flip, binning, white level) recorded with every kernel
file and checkpoint; commands that consume one read files the same way by default, and a flag
that contradicts the record wins with a one-line notice (:func:`choose`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from psfkit.errors import InvalidInputError
from psfkit.io.validation import MAX_DOWNSAMPLE, MAX_WHITE_LEVEL

CHANNEL_ORDERS = ("RGB", "BGR")
FLIPS = ("none", "ud", "lr", "both")


@dataclass(frozen=True)
class ReadOptions:
    """The read options of one data set.

    Attributes
    ----------
    channel_order : {"RGB", "BGR"} or None
        Channel order of the ``.npy``/TIFF files on disk; ``None``: not recorded.
    flip : {"none", "ud", "lr", "both"}
        Flip applied to the scenes so that they match the measurements.
    downsample : int or None
        Block-mean binning factor; ``None``: not recorded (the consumer's default, 1).
    white_level : float or None
        Stored value of full scale of integer files (``None``: the dtype's maximum).
    """

    channel_order: str | None = None
    flip: str = "none"
    downsample: int | None = None
    white_level: float | None = None

    def __post_init__(self) -> None:
        if self.channel_order is not None and self.channel_order not in CHANNEL_ORDERS:
            raise InvalidInputError(f"channel order must be RGB or BGR, got "
                                    f"{self.channel_order!r}")
        if self.flip not in FLIPS:
            raise InvalidInputError(f"flip must be one of {', '.join(FLIPS)}, got {self.flip!r}")
        if self.downsample is not None and (
                isinstance(self.downsample, bool) or not isinstance(self.downsample, int)
                or not 1 <= self.downsample <= MAX_DOWNSAMPLE):
            raise InvalidInputError(f"downsample must be an integer in 1..{MAX_DOWNSAMPLE}, got "
                                    f"{self.downsample!r}")
        if self.white_level is not None and (
                isinstance(self.white_level, bool)
                or not isinstance(self.white_level, (int, float))
                or not math.isfinite(self.white_level)
                or not 0 < self.white_level <= MAX_WHITE_LEVEL):
            raise InvalidInputError(f"white level must be a number in (0, 2^32], got "
                                    f"{self.white_level!r}")

    def to_json(self) -> dict[str, Any]:
        """JSON-able dict (the ``read_options`` field of kernel files and checkpoints)."""
        return asdict(self)

    @classmethod
    def from_json(cls, doc: Any, where: str) -> ReadOptions:
        """Parse a recorded ``read_options`` object (unknown keys ignored); a bad one raises
        :class:`InvalidInputError` naming ``where``."""
        if not isinstance(doc, dict):
            raise InvalidInputError(f"{where}: 'read_options' must be an object, got {doc!r}")
        known = {k: doc[k] for k in ("channel_order", "flip", "downsample", "white_level")
                 if k in doc}
        try:
            return cls(**known)
        except InvalidInputError as exc:
            raise InvalidInputError(f"{where}: read_options: {exc}") from None


def choose(flag: Any, recorded: Any, default: Any, flag_name: str,
           source: str) -> tuple[Any, str | None]:
    """One read option: the user's flag, else the recorded value, else the default.

    Returns ``(value, notice)``; ``notice`` is a one-line message when the flag (which wins)
    contradicts the record, else ``None``.
    """
    if flag is None:
        return (default if recorded is None else recorded), None
    if recorded is not None and flag != recorded:
        return flag, (f"note: {flag_name} {flag} differs from the {recorded} recorded in "
                      f"{source} (how its data was read); using {flag}")
    return flag, None
