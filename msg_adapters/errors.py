"""The msg_adapters error hierarchy: one base class, a few specific subclasses.

Every message names the message field and the offending value, e.g.
``UnsupportedEncodingError("image.encoding 'yuv422' is not supported; supported: ...")``.
All derive from ValueError, so callers that only care about "bad input" catch that.
"""


class AdapterError(ValueError):
    """Base class of every error raised by msg_adapters."""


class UnsupportedEncodingError(AdapterError):
    """An image encoding or compressed format this package does not handle."""


class LayoutError(AdapterError):
    """Sizes do not agree: step, row_step, point_step, data length, array shape or dtype."""


class CameraInfoError(AdapterError):
    """A CameraInfo cannot be turned into a camera model (zero K, unknown model, bad D)."""


class FieldError(AdapterError):
    """A message field holds a value outside its valid range (stamp, level, heading...)."""
