"""The exceptions invglare raises for user mistakes.

Every error names the offending value and what was expected. The CLI prints
``str(error)`` as one line and exits non-zero; anything that is *not* an
:class:`InvglareError` is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


class InvglareError(Exception):
    """Base class of every error a user can cause and fix."""


class ConfigError(InvglareError, ValueError):
    """A configuration (TOML file or CLI option) is malformed: unknown key, wrong type."""


class InputDataError(InvglareError, ValueError):
    """A data file (EXR, PNG, aperture image) is missing, unreadable or holds bad values."""


class PhysicsRangeError(InvglareError, ValueError):
    """A physical quantity is outside its meaningful range (negative size, wavelength in metres)."""


class NumericalError(InvglareError, RuntimeError):
    """A computation produced non-finite values or cannot be sampled adequately."""


class MemoryLimitError(InvglareError, ValueError):
    """A requested size needs more memory than allowed (see :mod:`invglare._core.memory`)."""


class FolderBusyError(InvglareError, RuntimeError):
    """An output folder is in use by another run (:func:`invglare.files.atomic.folder_lock`)."""


@contextlib.contextmanager
def prefixed(where: str) -> Iterator[None]:
    """Put `where` (an option or key, e.g. ``"--npix"``) in front of an InvglareError raised
    in the body, unless the message already starts with it."""
    try:
        yield
    except InvglareError as err:
        if str(err).startswith(where):
            raise
        raise type(err)(f"{where}: {err}") from None


class RasterWarning(UserWarning):
    """A structure of the aperture that the raster or the output field cannot show in full.

    The model still runs (its blocked power is right); the message names the raster or
    field that would show it.
    """
