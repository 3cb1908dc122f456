"""Image / CompressedImage adapters: every encoding, both byte orders, step padding, errors."""

from __future__ import annotations

import array

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, Image

from msg_adapters.errors import AdapterError, LayoutError, UnsupportedEncodingError
from msg_adapters.image import (
    ENCODINGS,
    TRACKABLE_ENCODINGS,
    array_to_compressed,
    array_to_image,
    compressed_to_array,
    compressed_to_frame,
    image_to_array,
    image_to_frame,
    to_mono8,
)
from msg_adapters.stamps import make_header

H, W = 7, 5


def _random(encoding: str, seed: int = 0) -> np.ndarray:
    fmt = ENCODINGS[encoding]
    rng = np.random.default_rng(seed)
    shape = (H, W) if fmt.channels == 1 else (H, W, fmt.channels)
    if fmt.dtype.kind == "f":
        return rng.normal(10.0, 3.0, shape).astype(fmt.dtype)
    info = np.iinfo(fmt.dtype)
    # full range so that both bytes of 16-bit values vary (byte order matters)
    return rng.integers(info.min, info.max, shape, endpoint=True).astype(fmt.dtype)


@pytest.mark.parametrize("encoding", list(ENCODINGS))
@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("pad", [0, 3])
def test_round_trip_every_encoding_byte_order_and_padding(encoding, bigendian, pad):
    arr = _random(encoding)
    row = W * ENCODINGS[encoding].pixel_bytes
    header = make_header(1_700_000_000_123_456_789, "cam")
    msg = array_to_image(arr, encoding, header, is_bigendian=bigendian, step=row + pad)
    assert (msg.width, msg.height, msg.step, msg.is_bigendian) == (W, H, row + pad, bigendian)
    assert len(msg.data) == (row + pad) * H
    # through the wire format too: what a subscriber receives
    wire = deserialize_message(serialize_message(msg), Image)
    for m in (msg, wire):
        out = image_to_array(m)
        assert out.dtype == arr.dtype and out.dtype.isnative
        np.testing.assert_array_equal(out, arr)
    assert wire.header.stamp.sec == 1_700_000_000 and wire.header.stamp.nanosec == 123_456_789


@pytest.mark.parametrize("encoding", ["mono16", "32FC1"])
def test_byte_order_is_read_from_the_message_not_assumed(encoding):
    arr = _random(encoding, seed=3)
    big = array_to_image(arr, encoding, is_bigendian=True)
    little = array_to_image(arr, encoding, is_bigendian=False)
    assert bytes(big.data) != bytes(little.data)
    # the big-endian bytes really are big-endian on the wire
    expected = arr.astype(arr.dtype.newbyteorder(">")).tobytes()
    assert bytes(big.data) == expected
    # a message lying about its byte order decodes to the swapped values
    big.is_bigendian = 0
    np.testing.assert_array_equal(image_to_array(big), arr.byteswap())


def test_hand_built_big_endian_mono16_with_padding():
    # 2 x 2 mono16, step 6 (2 padding bytes), values 0x0102 0x0304 / 0x0506 0x0708
    data = bytes([1, 2, 3, 4, 0xEE, 0xEE, 5, 6, 7, 8, 0xEE, 0xEE])
    msg = Image(height=2, width=2, encoding="mono16", is_bigendian=1, step=6)
    msg.data = array.array("B", data)
    np.testing.assert_array_equal(image_to_array(msg), [[0x0102, 0x0304], [0x0506, 0x0708]])


def test_message_is_not_mutated_and_result_owns_its_memory():
    arr = _random("mono16")
    msg = array_to_image(arr, "mono16", is_bigendian=True, step=W * 2 + 2)
    before = bytes(msg.data)
    out = image_to_array(msg)
    out[...] = 0  # writable copy
    assert bytes(msg.data) == before
    assert not np.shares_memory(out, np.frombuffer(msg.data, np.uint8))
    # also for the unpadded mono8 case where no byte swap or unpadding is needed
    m8 = array_to_image(_random("mono8"), "mono8")
    before8 = bytes(m8.data)
    out8 = image_to_array(m8)
    out8[...] = 1
    assert bytes(m8.data) == before8


def test_single_channel_accepts_trailing_axis():
    arr = _random("mono8")
    msg = array_to_image(arr[:, :, None], "mono8")
    np.testing.assert_array_equal(image_to_array(msg), arr)


def test_unknown_encoding_names_the_value():
    msg = Image(height=1, width=1, encoding="yuv422", step=2)
    msg.data = array.array("B", b"\0\0")
    with pytest.raises(UnsupportedEncodingError, match="yuv422"):
        image_to_array(msg)
    with pytest.raises(UnsupportedEncodingError, match="bayer_rggb8"):
        array_to_image(np.zeros((2, 2), np.uint8), "bayer_rggb8")


def test_step_too_small_names_step_and_value():
    msg = array_to_image(_random("rgb8"), "rgb8")
    msg.step = W * 3 - 1
    with pytest.raises(LayoutError, match=rf"image.step {W * 3 - 1}"):
        image_to_array(msg)
    with pytest.raises(LayoutError, match="step 4"):
        array_to_image(_random("rgb8"), "rgb8", step=4)


def test_data_length_mismatch_names_the_sizes():
    msg = array_to_image(_random("bgr8"), "bgr8")
    msg.data = msg.data[:-1]
    with pytest.raises(LayoutError, match=rf"{H * W * 3 - 1} bytes"):
        image_to_array(msg)


@pytest.mark.parametrize(
    ("shape", "dtype", "encoding", "match"),
    [
        ((H, W), np.uint8, "rgb8", r"\(H, W, 3\)"),
        ((H, W, 4), np.uint8, "rgb8", r"\(7, 5, 4\)"),
        ((H, W), np.uint16, "mono8", "uint16"),
        ((H, W), np.float64, "32FC1", "float64"),
    ],
)
def test_array_shape_and_dtype_are_checked(shape, dtype, encoding, match):
    with pytest.raises(LayoutError, match=match):
        array_to_image(np.zeros(shape, dtype), encoding)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_to_mono8_colour_uses_channel_order(encoding):
    rgb = _random("rgb8", seed=5)
    codes = {
        "rgb8": None,
        "bgr8": cv2.COLOR_RGB2BGR,
        "rgba8": cv2.COLOR_RGB2RGBA,
        "bgra8": cv2.COLOR_RGB2BGRA,
    }
    arr = rgb if codes[encoding] is None else cv2.cvtColor(rgb, codes[encoding])
    grey = to_mono8(arr, encoding)
    # BT.601 weights on the RGB values, rounded: cv2 uses fixed point, within 1 level
    ref = rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])
    assert grey.dtype == np.uint8 and grey.shape == (H, W)
    assert np.abs(grey.astype(np.float64) - ref).max() <= 1.0


def test_to_mono8_mono16_fixed_scale():
    arr = np.array([[0, 257, 65535], [128, 32896, 65278]], dtype=np.uint16)
    np.testing.assert_array_equal(to_mono8(arr, "mono16"), [[0, 1, 255], [0, 128, 254]])
    twelve = np.array([[0, 4095, 2048, 65535]], dtype=np.uint16)
    # 12-bit sensor: 4095 -> 255, 2048 -> round(127.56) = 128, out of range clips
    np.testing.assert_array_equal(
        to_mono8(twelve, "mono16", significant_bits=12), [[0, 255, 128, 255]]
    )
    with pytest.raises(AdapterError, match="17"):
        to_mono8(arr, "mono16", significant_bits=17)


def test_to_mono8_rejects_range_images():
    with pytest.raises(UnsupportedEncodingError, match="32FC1"):
        to_mono8(np.zeros((2, 2), np.float32), "32FC1")


def test_image_to_frame_stamp_and_grey():
    arr = _random("bgr8", seed=9)
    msg = array_to_image(arr, "bgr8", make_header(5_000_000_001, "c"), step=W * 3 + 1)
    frame = image_to_frame(msg)
    assert frame.stamp_ns == 5_000_000_001
    np.testing.assert_array_equal(frame.image, cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY))
    assert set(TRACKABLE_ENCODINGS) == set(ENCODINGS) - {"32FC1"}


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8"])
def test_png_round_trip_is_exact(encoding):
    arr = _random(encoding, seed=11)
    msg = array_to_compressed(arr, encoding, "png", make_header(42, "cam"))
    wire = deserialize_message(serialize_message(msg), CompressedImage)
    out, enc = compressed_to_array(wire)
    assert enc == encoding
    np.testing.assert_array_equal(out, arr)


def test_jpeg_decodes_close_to_the_original():
    # smooth image: jpeg error at quality 95 is a few grey levels
    yy, xx = np.mgrid[0:48, 0:64]
    arr = ((xx * 3 + yy * 2) % 256).astype(np.uint8)
    msg = array_to_compressed(arr, "mono8", "jpeg", quality=95)
    assert msg.format == "mono8; jpeg compressed mono8"
    out, enc = compressed_to_array(msg)
    assert enc == "mono8" and out.shape == arr.shape
    assert np.abs(out.astype(int) - arr.astype(int)).mean() < 2.0
    frame = compressed_to_frame(msg)
    np.testing.assert_array_equal(frame.image, out)


def test_plain_jpeg_format_from_a_driver():
    rgb = _random("rgb8", seed=2)
    ok, enc = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    msg = CompressedImage(format="png")
    msg.data = array.array("B", enc.tobytes())
    out, encoding = compressed_to_array(msg)
    assert encoding == "bgr8"
    np.testing.assert_array_equal(out, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def test_compressed_errors():
    msg = CompressedImage(format="tiff")
    msg.data = array.array("B", b"abc")
    with pytest.raises(UnsupportedEncodingError, match="'tiff'"):
        compressed_to_array(msg)
    msg.format = "jpeg"
    with pytest.raises(LayoutError, match="3 bytes"):
        compressed_to_array(msg)
    with pytest.raises(UnsupportedEncodingError, match="jpeg"):
        array_to_compressed(np.zeros((4, 4), np.uint16), "mono16", "jpeg")


@pytest.mark.parametrize(
    "fmt", ["16UC1; compressedDepth", "16UC1; compressedDepth png", "32FC1; compressedDepth png"]
)
def test_compressed_depth_is_refused_by_name(fmt):
    # compressed_depth_image_transport: a 12-byte config header, then png (not decodable)
    ok, png = cv2.imencode(".png", np.full((4, 4), 1000, np.uint16))
    assert ok
    msg = CompressedImage(format=fmt)
    msg.data = array.array("B", bytes(12) + png.tobytes())
    with pytest.raises(UnsupportedEncodingError, match="compressedDepth"):
        compressed_to_array(msg)


def test_compressed_with_an_unsupported_declared_encoding_is_refused():
    # image_transport writes a Bayer mosaic as "bayer_rggb8; jpeg compressed ": it decodes
    # as one grey channel, but it is not a grey image (a raw bayer_rggb8 Image is refused)
    ok, jpg = cv2.imencode(".jpg", _random("mono8", seed=4))
    assert ok
    msg = CompressedImage(format="bayer_rggb8; jpeg compressed ")
    msg.data = array.array("B", jpg.tobytes())
    with pytest.raises(UnsupportedEncodingError, match="bayer_rggb8"):
        compressed_to_array(msg)
    msg.format = "mono8; jpeg compressed "  # what image_transport writes for mono8
    assert compressed_to_array(msg)[1] == "mono8"


def test_corrupted_compressed_header_is_a_layout_error_not_cv2_error():
    ok, jpg = cv2.imencode(".jpg", np.zeros((8, 8), np.uint8))
    assert ok
    data = bytearray(jpg.tobytes())
    sof = data.find(b"\xff\xc0")
    data[sof + 5 : sof + 9] = (65000).to_bytes(2, "big") * 2  # 65000 x 65000 pixels
    msg = CompressedImage(format="jpeg")
    msg.data = array.array("B", bytes(data))
    with pytest.raises(LayoutError, match="does not decode"):
        compressed_to_array(msg)
