"""FrameResult -> PointCloud2 -> structured array: every contract field, layouts, errors."""

from __future__ import annotations

import array

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2, PointField

from msg_adapters.errors import FieldError, LayoutError
from msg_adapters.pointcloud import (
    OWL_DTYPE,
    OWL_FIELDS,
    array_to_cloud,
    cloud_speed,
    cloud_to_array,
    frame_result_to_cloud,
)
from msg_adapters.stamps import make_header
from owl_core.types import FrameResult, PointFlag

CONTRACT_FLOAT32 = (
    "x y z u v L omega_x omega_y omega_z rot_w rot_x rot_y rot_z range_over_speed quality".split()
)


def _result(n: int = 9, seed: int = 0) -> FrameResult:
    rng = np.random.default_rng(seed)
    e = rng.normal(size=(n, 3))
    e[:, 2] = np.abs(e[:, 2]) + 1.0
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    looming = rng.normal(0.3, 0.2, n)
    omega = np.cross(e, rng.normal(size=3)) * 0.1
    den = looming**2 + np.sum(omega**2, axis=1)
    rot = np.column_stack([looming, -omega]) / den[:, None]
    ros = 1.0 / np.sqrt(den)
    return FrameResult(
        stamp_ns=1_234,
        pixels=rng.uniform(0, 320, (n, 2)),
        bearings=e,
        looming=looming,
        omega=omega,
        rot=rot,
        range_over_speed=ros,
        points=e * ros[:, None],
        quality=rng.uniform(0, 1, n),
        ids=rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32),
        flags=rng.integers(0, 64, n).astype(np.uint8),
        heading=np.array([0.0, 0.0, 1.0]),
        heading_sigma_rad=0.01,
        gyro_bias=np.zeros(3),
    )


def _expected(res: FrameResult, speed: float | None) -> dict[str, np.ndarray]:
    xyz = res.points * (1.0 if speed is None else speed)
    cols = {
        "x": xyz[:, 0],
        "y": xyz[:, 1],
        "z": xyz[:, 2],
        "u": res.pixels[:, 0],
        "v": res.pixels[:, 1],
        "L": res.looming,
        "omega_x": res.omega[:, 0],
        "omega_y": res.omega[:, 1],
        "omega_z": res.omega[:, 2],
        "rot_w": res.rot[:, 0],
        "rot_x": res.rot[:, 1],
        "rot_y": res.rot[:, 2],
        "rot_z": res.rot[:, 3],
        "range_over_speed": res.range_over_speed,
        "quality": res.quality,
    }
    return {k: v.astype(np.float32) for k, v in cols.items()}


def test_layout_has_every_contract_field_with_its_type():
    fields = {f[0]: np.dtype(f[1]) for f in OWL_FIELDS}
    for name in CONTRACT_FLOAT32:
        assert fields[name] == np.float32, name
    assert fields["id"] == np.uint32 and fields["flags"] == np.uint8
    # offsets packed and naturally aligned; point_step padded to a multiple of 4
    offsets = [OWL_DTYPE.fields[name][1] for name in OWL_DTYPE.names]
    assert offsets == [4 * i for i in range(17)] + [68]
    assert OWL_DTYPE.itemsize == 72


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("speed", [None, 2.5])
def test_frame_result_round_trip(bigendian, speed):
    res = _result()
    header = make_header(res.stamp_ns, "camera_optical")
    msg = frame_result_to_cloud(res, header, speed=speed, is_bigendian=bigendian)
    assert (msg.height, msg.width, msg.point_step) == (1, 9, 72)
    assert msg.row_step == 72 * 9 and len(msg.data) == 72 * 9
    assert msg.is_bigendian == bigendian and msg.is_dense
    assert msg.header.frame_id == "camera_optical"
    by_name = {f.name: f for f in msg.fields}
    assert by_name["id"].datatype == PointField.UINT32 and by_name["id"].offset == 64
    assert by_name["flags"].datatype == PointField.UINT8 and by_name["flags"].offset == 68
    assert all(by_name[n].datatype == PointField.FLOAT32 for n in CONTRACT_FLOAT32)
    wire = deserialize_message(serialize_message(msg), PointCloud2)
    pts = cloud_to_array(wire)
    assert pts.shape == (9,)
    for name, values in _expected(res, speed).items():
        np.testing.assert_array_equal(pts[name], values, err_msg=name)
        assert pts[name].dtype == np.float32 and pts[name].dtype.isnative
    np.testing.assert_array_equal(pts["id"], res.ids)
    np.testing.assert_array_equal(pts["flags"], res.flags)
    assert cloud_speed(pts) == speed
    if speed is None:
        assert np.isnan(pts["speed"]).all()


def test_big_endian_bytes_really_are_big_endian():
    res = _result(2)
    msg = frame_result_to_cloud(res, make_header(0, "c"), is_bigendian=True)
    raw = bytes(msg.data)
    x0 = np.frombuffer(raw[0:4], ">f4")[0]
    id1 = np.frombuffer(raw[72 + 64 : 72 + 68], ">u4")[0]
    assert x0 == np.float32(res.points[0, 0]) and id1 == res.ids[1]


def test_empty_result_gives_an_empty_valid_cloud():
    res = _result(0)
    msg = frame_result_to_cloud(res, make_header(0, "c"))
    assert msg.width == 0 and len(msg.data) == 0 and len(msg.fields) == len(OWL_FIELDS)
    assert cloud_to_array(msg).shape == (0,)


def test_non_finite_points_clear_is_dense():
    res = _result(3)
    res.points[1, 2] = np.nan
    assert not frame_result_to_cloud(res, make_header(0, "c")).is_dense


def test_reader_honours_foreign_layouts_padding_and_row_step():
    """A cloud as another driver might write it: float64 + int16, odd order, padding."""
    n_rows, n_cols, point_step = 2, 3, 24
    row_step = n_cols * point_step + 5
    rng = np.random.default_rng(4)
    x = rng.normal(size=(n_rows, n_cols))
    ring = rng.integers(-300, 300, (n_rows, n_cols)).astype(np.int16)
    rgb = rng.integers(0, 255, (n_rows, n_cols, 3)).astype(np.uint8)
    for bigendian in (False, True):
        o = ">" if bigendian else "<"
        data = bytearray(row_step * n_rows)
        for r in range(n_rows):
            for c in range(n_cols):
                base = r * row_step + c * point_step
                data[base + 8 : base + 16] = np.array(x[r, c], o + "f8").tobytes()
                data[base + 2 : base + 4] = np.array(ring[r, c], o + "i2").tobytes()
                data[base + 16 : base + 19] = rgb[r, c].tobytes()
        msg = PointCloud2(height=n_rows, width=n_cols, point_step=point_step, row_step=row_step)
        msg.is_bigendian = bigendian
        msg.fields = [
            PointField(name="x", offset=8, datatype=PointField.FLOAT64, count=1),
            PointField(name="ring", offset=2, datatype=PointField.INT16, count=1),
            PointField(name="rgb", offset=16, datatype=PointField.UINT8, count=3),
        ]
        msg.data = array.array("B", bytes(data))
        before = bytes(msg.data)
        pts = cloud_to_array(msg)
        assert bytes(msg.data) == before
        assert pts.dtype.names == ("x", "ring", "rgb")
        np.testing.assert_array_equal(pts["x"], x.reshape(-1))
        np.testing.assert_array_equal(pts["ring"], ring.reshape(-1))
        np.testing.assert_array_equal(pts["rgb"], rgb.reshape(-1, 3))


def test_array_to_cloud_with_extra_point_step_round_trips():
    pts = np.zeros(4, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("i", "u2")])
    pts["x"], pts["i"] = [1, 2, 3, 4], [9, 8, 7, 6]
    msg = array_to_cloud(pts, make_header(0, "m"), is_bigendian=True, point_step=20)
    assert msg.point_step == 20 and len(msg.data) == 80
    back = cloud_to_array(msg)
    np.testing.assert_array_equal(back, pts)


@pytest.mark.parametrize(
    ("attr", "value", "match"),
    [
        ("row_step", 71, r"row_step 71 is smaller than width 1 \* point_step 72"),
        ("point_step", 60, r"fields\['speed'\] ends at byte 64, beyond point_step 60"),
        ("data", b"\0" * 71, "71 bytes, expected row_step 72"),
    ],
)
def test_reader_layout_errors_name_the_value(attr, value, match):
    msg = frame_result_to_cloud(_result(1), make_header(0, "c"))
    setattr(msg, attr, array.array("B", value) if attr == "data" else value)
    with pytest.raises(LayoutError, match=match):
        cloud_to_array(msg)


def test_reader_rejects_unknown_datatype_and_duplicate_names():
    msg = frame_result_to_cloud(_result(1), make_header(0, "c"))
    msg.fields[3].datatype = 9
    with pytest.raises(LayoutError, match=r"fields\['u'\].datatype 9"):
        cloud_to_array(msg)
    msg = frame_result_to_cloud(_result(1), make_header(0, "c"))
    msg.fields[1].name = "x"
    with pytest.raises(LayoutError, match="'x' twice"):
        cloud_to_array(msg)


def test_writer_errors():
    res = _result(3)
    with pytest.raises(FieldError, match=r"got -1\.0"):
        frame_result_to_cloud(res, make_header(0, "c"), speed=-1.0)
    bad = FrameResult(**{**res.__dict__, "quality": np.zeros(2)})
    with pytest.raises(LayoutError, match=r"FrameResult.quality must have shape \(3,\)"):
        frame_result_to_cloud(bad, make_header(0, "c"))
    with pytest.raises(LayoutError, match="structured"):
        array_to_cloud(np.zeros(3), make_header(0, "c"))


def test_flags_bits_survive():
    res = _result(2)
    res.flags[:] = [PointFlag.L_LOCAL | PointFlag.MOVING, PointFlag.IMU_GAP]
    pts = cloud_to_array(frame_result_to_cloud(res, make_header(0, "c")))
    assert pts["flags"].tolist() == [5, 32]


def test_reader_skips_pcl_padding_fields_and_unnamed_fields():
    # PCL marks padding with fields named "_" (several of them); one unnamed field too
    x = np.arange(3, dtype="<f4") + 0.5
    data = bytearray(3 * 32)
    for i in range(3):
        data[32 * i : 32 * i + 4] = x[i].tobytes()
        data[32 * i + 16 : 32 * i + 20] = np.uint32(7 + i).tobytes()
    msg = PointCloud2(height=1, width=3, point_step=32, row_step=96)
    msg.fields = [
        PointField(name="x", offset=0, datatype=PointField.FLOAT32, count=1),
        PointField(name="_", offset=4, datatype=PointField.UINT8, count=4),
        PointField(name="", offset=8, datatype=PointField.FLOAT32, count=1),
        PointField(name="rgb", offset=16, datatype=PointField.UINT32, count=1),
        PointField(name="_", offset=20, datatype=PointField.UINT8, count=12),
    ]
    msg.data = array.array("B", bytes(data))
    pts = cloud_to_array(msg)
    assert pts.dtype.names == ("x", "rgb")
    np.testing.assert_array_equal(pts["x"], x)
    np.testing.assert_array_equal(pts["rgb"], [7, 8, 9])


def test_count_zero_field_is_refused_not_read_as_empty():
    msg = frame_result_to_cloud(_result(1), make_header(0, "c"))
    msg.fields[0].count = 0
    with pytest.raises(LayoutError, match=r"fields\['x'\].count is 0"):
        cloud_to_array(msg)


def test_writer_refuses_multidimensional_subarrays():
    pts = np.zeros(2, dtype=[("x", "f4"), ("m", "f4", (2, 2))])
    with pytest.raises(LayoutError, match=r"'m' has shape \(2, 2\)"):
        array_to_cloud(pts, make_header(0, "c"))
