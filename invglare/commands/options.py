"""Command-line options checked before any work, with messages that name the option typed.

The library's own checks name its arguments (``npix``, ``max_count``); a user of the
command typed ``--npix`` and ``--max-bright``. Each command checks its options here first
(ranges, finiteness, the memory a size needs), and :func:`named` puts the option's name
in front of a library error raised while its value is interpreted.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Iterator

import numpy as np

from invglare._core.memory import check_memory
from invglare.errors import ConfigError, InvglareError, PhysicsRangeError, prefixed

#: Bytes of one float32 sample, and of one complex64 sample.
F32, C64 = 4, 8


#: Put the option's name in front of a library error raised while its value is read.
named = prefixed


@contextlib.contextmanager
def given(*options: tuple[str, object, str]) -> Iterator[None]:
    """Name the options behind a library error raised in the body.

    `options`: ``(option, value, internal name)`` of each option given (value not None);
    an error whose message names the internal name (``npix``) gets ``(from --npix 4096)``.
    """
    try:
        yield
    except InvglareError as err:
        text = str(err)
        hits = [
            f"{opt} {value}"
            for opt, value, inner in options
            if value is not None and re.search(rf"\b{re.escape(inner)}", text)
        ]
        if not hits:
            raise
        raise type(err)(f"{text} (from {', '.join(hits)})") from None


def count(value: int | None, option: str, minimum: int = 1) -> int | None:
    """`value` unless it is below `minimum` (None passes: the option was not given)."""
    if value is not None and (isinstance(value, bool) or value < minimum):
        raise ConfigError(f"{option} must be an integer >= {minimum}, got {value!r}")
    return value


def positive(value: float | None, option: str, *, zero: bool = False) -> float | None:
    """`value` unless it is not finite or not > 0 (>= 0 with `zero`); None passes."""
    if value is None:
        return None
    if not math.isfinite(value) or value < 0 or (value == 0 and not zero):
        raise PhysicsRangeError(
            f"{option} must be a finite number {'>=' if zero else '>'} 0, got {value!r}"
        )
    return value


def wavelengths(text: str | None, option: str = "--wavelengths-nm") -> np.ndarray | None:
    """The wavelengths (nm) of a ``--wavelengths-nm`` value; None passes."""
    if text is None:
        return None
    from invglare.optics.spectral import parse_wavelengths

    with named(option):
        return parse_wavelengths(text)


def raster(npix: int, option: str, *, channels: int = 1, itemsize: int = F32, copies: int = 4):
    """Refuse an image of `npix`² pixels whose buffers would not fit in memory.

    `copies`: how many such buffers the work holds at once (a lower bound: the estimate
    only has to refuse what cannot work, before it is tried).
    """
    check_memory(
        float(npix) ** 2 * channels * itemsize * copies,
        f"an image of {npix}x{npix} pixels x {channels} channel(s) ({option} {npix})",
    )
