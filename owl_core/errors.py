"""The owl_core error hierarchy: one base class, a few specific subclasses.

Messages say what was wrong and with which value, e.g.
``InvalidInputError("pixels must have shape (N, 2), got (5, 3)")``.
"""


class OwlError(Exception):
    """Base class of every error raised by owl_core."""


class InvalidInputError(OwlError, ValueError):
    """An argument has the wrong shape, dtype, unit range or value."""


class CalibrationError(OwlError, ValueError):
    """A camera model or extrinsic cannot be built from the given values."""


class TimeError(OwlError, ValueError):
    """Stamps are out of order, or a requested interval is not covered by data."""
