"""The exceptions invglare raises for user mistakes.

Every error names the offending value and what was expected. The CLI prints
``str(error)`` as one line and exits non-zero; anything that is *not* an
:class:`InvglareError` is a bug and keeps its traceback.
"""

from __future__ import annotations


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


class RasterWarning(UserWarning):
    """A structure of the aperture that the raster or the output field cannot show in full.

    The model still runs (its blocked power is right); the message names the raster or
    field that would show it.
    """
