"""sensor_msgs/Image and CompressedImage <-> numpy arrays, driven by one encoding table.

``image_to_array`` honours ``step`` (row padding) and ``is_bigendian`` and never mutates
the message: it reads the buffer through a read-only view and returns a native-byte-order
copy. ``array_to_image`` is its inverse for any step >= width * bytes per pixel and either
byte order. ``to_mono8`` turns any supported array into the (H, W) uint8 grey image the
engine tracks on.
"""

from __future__ import annotations

import array
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt
from sensor_msgs.msg import CompressedImage, Image

from msg_adapters.errors import AdapterError, LayoutError, UnsupportedEncodingError
from msg_adapters.stamps import header_to_ns
from owl_core.types import ImageFrame

AnyArray = npt.NDArray[Any]


@dataclass(frozen=True)
class PixelFormat:
    """One row of the encoding table.

    Attributes:
        dtype: element type of one channel (native byte order).
        channels: channels per pixel.
        gray_code: cv2.cvtColor code to grey, or None when already single-channel.
    """

    dtype: np.dtype[Any]
    channels: int
    gray_code: int | None = None

    @property
    def pixel_bytes(self) -> int:
        """Bytes per pixel."""
        return self.dtype.itemsize * self.channels


#: encoding -> pixel format. The only place encodings are listed.
ENCODINGS: dict[str, PixelFormat] = {
    "mono8": PixelFormat(np.dtype(np.uint8), 1),
    "8UC1": PixelFormat(np.dtype(np.uint8), 1),
    "mono16": PixelFormat(np.dtype(np.uint16), 1),
    "16UC1": PixelFormat(np.dtype(np.uint16), 1),
    "rgb8": PixelFormat(np.dtype(np.uint8), 3, cv2.COLOR_RGB2GRAY),
    "bgr8": PixelFormat(np.dtype(np.uint8), 3, cv2.COLOR_BGR2GRAY),
    "rgba8": PixelFormat(np.dtype(np.uint8), 4, cv2.COLOR_RGBA2GRAY),
    "bgra8": PixelFormat(np.dtype(np.uint8), 4, cv2.COLOR_BGRA2GRAY),
    "32FC1": PixelFormat(np.dtype(np.float32), 1),
}

#: encodings the engine can track on (to_mono8 accepts them); 32FC1 is ground-truth range only.
TRACKABLE_ENCODINGS: tuple[str, ...] = (
    "mono8",
    "8UC1",
    "mono16",
    "16UC1",
    "rgb8",
    "bgr8",
    "rgba8",
    "bgra8",
)


def pixel_format(encoding: str) -> PixelFormat:
    """The table row of ``encoding``; UnsupportedEncodingError naming it if unknown."""
    try:
        return ENCODINGS[encoding]
    except KeyError:
        raise UnsupportedEncodingError(
            f"image.encoding {encoding!r} is not supported; supported: {', '.join(ENCODINGS)}"
        ) from None


def _byte_order(is_bigendian: bool | int) -> Literal["<", ">"]:
    return ">" if is_bigendian else "<"


def image_to_array(msg: Any) -> AnyArray:
    """sensor_msgs/Image -> (H, W) or (H, W, C) array in native byte order (a copy).

    Row padding (``step`` > width * bytes per pixel) is dropped; ``is_bigendian`` is
    honoured for multi-byte encodings. The message is not modified.

    Raises:
        UnsupportedEncodingError: unknown ``encoding``.
        LayoutError: ``step`` too small, or ``data`` length != step * height.
    """
    fmt = pixel_format(msg.encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * fmt.pixel_bytes
    if step < row_bytes:
        raise LayoutError(
            f"image.step {step} is smaller than width {width} * {fmt.pixel_bytes} bytes "
            f"({msg.encoding}) = {row_bytes}"
        )
    buf = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8)
    if buf.size != step * height:
        raise LayoutError(
            f"image.data has {buf.size} bytes, expected step {step} * height {height} "
            f"= {step * height}"
        )
    buf.flags.writeable = False  # a view into the message: never write through it
    rows = buf.reshape(height, step)[:, :row_bytes]
    wire = fmt.dtype.newbyteorder(_byte_order(msg.is_bigendian))
    # Reinterpret the unpadded part of each row in the wire byte order, then one copy into
    # a new native-order array (astype always copies): the message buffer is never touched.
    out = rows.view(wire).astype(fmt.dtype)
    shape = (height, width) if fmt.channels == 1 else (height, width, fmt.channels)
    return out.reshape(shape)


def _check_array(array_: AnyArray, encoding: str, fmt: PixelFormat) -> tuple[int, int]:
    if fmt.channels == 1 and array_.ndim == 3 and array_.shape[2] == 1:
        array_ = array_[:, :, 0]
    expected = "(H, W)" if fmt.channels == 1 else f"(H, W, {fmt.channels})"
    ok_shape = (
        array_.ndim == 2
        if fmt.channels == 1
        else (array_.ndim == 3 and array_.shape[2] == fmt.channels)
    )
    if not ok_shape:
        raise LayoutError(
            f"array for encoding {encoding!r} must have shape {expected}, got {array_.shape}"
        )
    if array_.dtype.newbyteorder("=") != fmt.dtype.newbyteorder("="):
        raise LayoutError(
            f"array for encoding {encoding!r} must have dtype {fmt.dtype.name}, "
            f"got {array_.dtype.name}"
        )
    return int(array_.shape[0]), int(array_.shape[1])


def array_to_image(
    array_: AnyArray,
    encoding: str,
    header: Any = None,
    is_bigendian: bool = False,
    step: int | None = None,
) -> Any:
    """(H, W) or (H, W, C) array -> sensor_msgs/Image.

    Args:
        array_: pixels; dtype must match the encoding exactly (no silent conversion).
        encoding: a key of ENCODINGS.
        header: std_msgs/Header to use (default: an empty header).
        is_bigendian: byte order written to ``data`` for multi-byte encodings.
        step: row length in bytes, >= width * bytes per pixel (default: exactly that);
            padding bytes are zero.

    Raises:
        UnsupportedEncodingError, LayoutError: naming the bad value.
    """
    fmt = pixel_format(encoding)
    arr = np.asarray(array_)
    height, width = _check_array(arr, encoding, fmt)
    row_bytes = width * fmt.pixel_bytes
    step_ = row_bytes if step is None else int(step)
    if step_ < row_bytes:
        raise LayoutError(
            f"step {step_} is smaller than width {width} * {fmt.pixel_bytes} bytes "
            f"({encoding}) = {row_bytes}"
        )
    wire = fmt.dtype.newbyteorder(_byte_order(is_bigendian))
    pixels = np.ascontiguousarray(arr, dtype=wire).view(np.uint8).reshape(height, row_bytes)
    if step_ == row_bytes:
        raw = pixels.tobytes()
    else:
        padded = np.zeros((height, step_), dtype=np.uint8)
        padded[:, :row_bytes] = pixels
        raw = padded.tobytes()
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height = height
    msg.width = width
    msg.encoding = encoding
    msg.is_bigendian = 1 if is_bigendian else 0
    msg.step = step_
    msg.data = array.array("B", raw)
    return msg


def to_mono8(array_: AnyArray, encoding: str, significant_bits: int = 16) -> npt.NDArray[np.uint8]:
    """Any trackable image array -> (H, W) uint8 grey, the engine's input.

    Colour goes through cv2.cvtColor (ITU-R BT.601 weights). 16-bit images are scaled
    linearly from [0, 2**significant_bits - 1] to [0, 255] with rounding and clipping
    (use e.g. 12 for a 12-bit sensor packed in mono16); the scale is fixed, never
    per-frame, so brightness stays comparable between frames for the tracker.

    Raises:
        UnsupportedEncodingError: encoding not in TRACKABLE_ENCODINGS (e.g. 32FC1).
        LayoutError: array shape/dtype do not match the encoding.
    """
    fmt = pixel_format(encoding)
    if encoding not in TRACKABLE_ENCODINGS:
        raise UnsupportedEncodingError(
            f"image.encoding {encoding!r} cannot be tracked; use one of "
            f"{', '.join(TRACKABLE_ENCODINGS)}"
        )
    arr = np.asarray(array_)
    _check_array(arr, encoding, fmt)
    if fmt.channels == 1 and arr.ndim == 3:
        arr = arr[:, :, 0]
    if fmt.gray_code is not None:
        return np.asarray(cv2.cvtColor(np.ascontiguousarray(arr), fmt.gray_code), np.uint8)
    if fmt.dtype == np.uint8:
        return np.ascontiguousarray(arr, dtype=np.uint8)
    if not 1 <= significant_bits <= 16:
        raise AdapterError(f"significant_bits must be in [1, 16], got {significant_bits}")
    full = float(2**significant_bits - 1)
    scaled = np.rint(arr.astype(np.float32) * np.float32(255.0 / full))
    grey: npt.NDArray[np.uint8] = np.clip(scaled, 0, 255).astype(np.uint8)
    return grey


def image_to_frame(msg: Any, significant_bits: int = 16) -> ImageFrame:
    """sensor_msgs/Image -> owl_core ImageFrame (header stamp, (H, W) uint8 grey)."""
    grey = to_mono8(image_to_array(msg), msg.encoding, significant_bits)
    return ImageFrame(stamp_ns=header_to_ns(msg.header), image=grey)


# ---------------------------------------------------------------------------------------------
# CompressedImage (image_transport "compressed": jpeg or png)

#: decoded array layout -> encoding, keyed by (ndim or channels, dtype)
_DECODED: dict[tuple[int, str], str] = {
    (1, "uint8"): "mono8",
    (1, "uint16"): "mono16",
    (3, "uint8"): "bgr8",
    (4, "uint8"): "bgra8",
}
#: encodings whose channel order cv2 stores swapped (RGB <-> BGR) -> (cv2 code out, code in)
_SWAPPED: dict[str, tuple[int, int, str]] = {
    "rgb8": (cv2.COLOR_RGB2BGR, cv2.COLOR_BGR2RGB, "bgr8"),
    "rgba8": (cv2.COLOR_RGBA2BGRA, cv2.COLOR_BGRA2RGBA, "bgra8"),
}
_CODECS: dict[str, str] = {"jpeg": ".jpg", "jpg": ".jpg", "png": ".png"}


def _codec(fmt: str) -> str:
    words = fmt.replace(";", " ").lower().split()
    if "compresseddepth" in words:
        # compressed_depth_image_transport ("16UC1; compressedDepth png|rvl"): a 12-byte
        # config header precedes the png/rvl data, and 32FC1 is stored as inverse depth
        raise UnsupportedEncodingError(
            f"compressed_image.format {fmt!r} is compressedDepth "
            "(compressed_depth_image_transport), which is not supported; expected jpeg or png"
        )
    for word in words:
        if word in _CODECS:
            return word
    raise UnsupportedEncodingError(
        f"compressed_image.format {fmt!r} is not supported; expected jpeg or png"
    )


def compressed_to_array(msg: Any) -> tuple[AnyArray, str]:
    """sensor_msgs/CompressedImage (jpeg or png) -> (array, encoding).

    ``format`` follows image_transport: ``"jpeg"``, ``"png"`` or ``"<enc>; <codec>
    compressed <cv-enc>"``. When the leading encoding is rgb8/rgba8 the channels are
    swapped back, so the result has that encoding; otherwise the decoded layout decides
    (mono8, mono16, bgr8, bgra8).

    Raises:
        UnsupportedEncodingError: format names neither jpeg nor png, is compressedDepth,
            or its leading encoding is not in ENCODINGS (e.g. a Bayer mosaic, which would
            otherwise decode as grey).
        LayoutError: the data does not decode.
    """
    fmt = str(msg.format)
    _codec(fmt)
    declared = fmt.split(";")[0].strip() if ";" in fmt else ""
    if declared and declared not in ENCODINGS:  # what image_to_array refuses, raw or not
        raise UnsupportedEncodingError(
            f"compressed_image.format {fmt!r}: encoding {declared!r} is not supported; "
            f"supported: {', '.join(ENCODINGS)}"
        )
    buf = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8)
    try:
        decoded = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    except cv2.error:  # e.g. a corrupted header claiming a huge size fails cv2's size check
        decoded = None
    if decoded is None:
        raise LayoutError(
            f"compressed_image.data ({buf.size} bytes, format {fmt!r}) does not decode"
        )
    channels = 1 if decoded.ndim == 2 else int(decoded.shape[2])
    encoding = _DECODED.get((channels, decoded.dtype.name))
    if encoding is None:
        raise UnsupportedEncodingError(
            f"compressed_image decodes to {channels} channel(s) of {decoded.dtype.name}, "
            "which has no supported encoding"
        )
    if declared in _SWAPPED and _SWAPPED[declared][2] == encoding:
        decoded = cv2.cvtColor(decoded, _SWAPPED[declared][1])
        encoding = declared
    return decoded, encoding


def array_to_compressed(
    array_: AnyArray, encoding: str, codec: str = "png", header: Any = None, quality: int = 95
) -> Any:
    """Array -> sensor_msgs/CompressedImage, image_transport style format string.

    ``codec`` is "png" (lossless: compressed_to_array returns the same array) or "jpeg"
    (``quality`` 0..100). Single-channel 16-bit works with png only.
    """
    fmt_row = pixel_format(encoding)
    arr = np.asarray(array_)
    _check_array(arr, encoding, fmt_row)
    ext = _CODECS.get(codec.lower())
    if ext is None:
        raise UnsupportedEncodingError(f"codec {codec!r} is not supported; expected jpeg or png")
    cv_enc = encoding
    if encoding in _SWAPPED:
        arr = cv2.cvtColor(np.ascontiguousarray(arr), _SWAPPED[encoding][0])
        cv_enc = _SWAPPED[encoding][2]
    if encoding == "32FC1" or (ext == ".jpg" and fmt_row.dtype != np.uint8):
        raise UnsupportedEncodingError(f"encoding {encoding!r} cannot be stored as {codec}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if ext == ".jpg" else []
    ok, encoded = cv2.imencode(ext, arr, params)
    if not ok:
        raise LayoutError(f"cv2.imencode failed for {encoding!r} as {codec}")
    msg = CompressedImage()
    if header is not None:
        msg.header = header
    msg.format = f"{encoding}; {codec.lower()} compressed {cv_enc}"
    msg.data = array.array("B", encoded.tobytes())
    return msg


def compressed_to_frame(msg: Any, significant_bits: int = 16) -> ImageFrame:
    """sensor_msgs/CompressedImage -> owl_core ImageFrame (header stamp, (H, W) uint8 grey)."""
    arr, encoding = compressed_to_array(msg)
    grey = to_mono8(arr, encoding, significant_bits)
    return ImageFrame(stamp_ns=header_to_ns(msg.header), image=grey)
