"""owl_core FrameResult -> sensor_msgs/PointCloud2, and any PointCloud2 -> structured array.

The OWL cloud layout is one table, ``OWL_FIELDS``; the structured dtype, the PointField
list, offsets and ``point_step`` all follow from it (as sensor_msgs_py builds dtypes from
fields). Readers honour ``is_bigendian``, ``point_step`` padding and ``row_step`` padding,
and return native-byte-order copies.

Units of ``x y z``: seconds (bearing * r/|t|) unless the cloud was scaled with a known
speed, in which case they are metres and the ``speed`` field holds that speed (m/s) in
every point; it is NaN in a cloud in seconds. ``cloud_speed`` reads it back.
"""

from __future__ import annotations

import array
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from sensor_msgs.msg import PointCloud2, PointField

from msg_adapters.errors import FieldError, LayoutError
from owl_core.types import FrameResult

AnyArray = npt.NDArray[Any]

#: PointField datatype constant <-> numpy element type (native order).
POINTFIELD_DTYPES: dict[int, np.dtype[Any]] = {
    PointField.INT8: np.dtype(np.int8),
    PointField.UINT8: np.dtype(np.uint8),
    PointField.INT16: np.dtype(np.int16),
    PointField.UINT16: np.dtype(np.uint16),
    PointField.INT32: np.dtype(np.int32),
    PointField.UINT32: np.dtype(np.uint32),
    PointField.FLOAT32: np.dtype(np.float32),
    PointField.FLOAT64: np.dtype(np.float64),
}
#: field names that mark padding, not data (PCL writes "_"), skipped when reading.
_PADDING_NAMES = frozenset({"", "_"})
_DATATYPE_OF: dict[str, int] = {dt.str[1:]: code for code, dt in POINTFIELD_DTYPES.items()}

#: The owl/points fields in wire order: (name, numpy type, unit and meaning).
OWL_FIELDS: tuple[tuple[str, type[np.generic], str], ...] = (
    ("x", np.float32, "bearing * r/|t| (s); metres when speed is finite"),
    ("y", np.float32, "as x"),
    ("z", np.float32, "as x"),
    ("u", np.float32, "pixel column in the (distorted) image, px"),
    ("v", np.float32, "pixel row, px"),
    ("L", np.float32, "looming (t.e)/r, 1/s, positive while approaching"),
    ("omega_x", np.float32, "perceived rotation (e x t)/r, 1/s"),
    ("omega_y", np.float32, "as omega_x"),
    ("omega_z", np.float32, "as omega_x"),
    ("rot_w", np.float32, "RoT = ToR^-1 scalar part, s"),
    ("rot_x", np.float32, "RoT vector part, s"),
    ("rot_y", np.float32, "as rot_x"),
    ("rot_z", np.float32, "as rot_x"),
    ("range_over_speed", np.float32, "r/|t|, s"),
    ("quality", np.float32, "0..1, 1 = rigid, well-fitted neighbourhood"),
    ("speed", np.float32, "speed |t| (m/s) that scaled x y z to metres; NaN if in seconds"),
    ("id", np.uint32, "persistent track id"),
    ("flags", np.uint8, "owl_core.types.PointFlag bits"),
)


def _aligned_dtype(fields: tuple[tuple[str, type[np.generic], str], ...]) -> np.dtype[Any]:
    """Packed offsets, each field aligned to its own size; itemsize rounded up to 4 bytes."""
    names, formats, offsets = [], [], []
    offset = 0
    for name, kind, _ in fields:
        size = np.dtype(kind).itemsize
        offset = -(-offset // size) * size
        names.append(name)
        formats.append(np.dtype(kind))
        offsets.append(offset)
        offset += size
    itemsize = -(-offset // 4) * 4
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": itemsize})


#: Structured dtype of one owl/points point (native order, explicit offsets, point_step 72).
OWL_DTYPE: np.dtype[Any] = _aligned_dtype(OWL_FIELDS)


def dtype_to_fields(dtype: np.dtype[Any]) -> list[Any]:
    """Structured dtype -> list of sensor_msgs/PointField (offsets from the dtype)."""
    out = []
    if dtype.names is None:
        raise LayoutError(f"point array must have a structured dtype, got {dtype}")
    for name in dtype.names:
        field_dtype, offset = dtype.fields[name][:2]  # type: ignore[index]
        base, shape = field_dtype.base, field_dtype.shape
        code = _DATATYPE_OF.get(base.newbyteorder("=").str[1:])
        if code is None:
            raise LayoutError(f"point field {name!r} has dtype {base}, not a PointField type")
        if len(shape) > 1:
            raise LayoutError(
                f"point field {name!r} has shape {shape}; a PointField holds a flat count"
            )
        count = int(shape[0]) if shape else 1
        out.append(PointField(name=name, offset=int(offset), datatype=code, count=count))
    return out


def fields_to_dtype(fields: Any, point_step: int, is_bigendian: bool | int) -> np.dtype[Any]:
    """PointField list -> structured dtype in the wire byte order with itemsize point_step."""
    order: Literal["<", ">"] = ">" if is_bigendian else "<"
    names, formats, offsets = [], [], []
    for field in fields:
        base = POINTFIELD_DTYPES.get(int(field.datatype))
        if base is None:
            raise LayoutError(
                f"point_cloud.fields[{field.name!r}].datatype {field.datatype} is not a "
                "PointField type (1..8)"
            )
        count = int(field.count)
        if count < 1:
            raise LayoutError(f"point_cloud.fields[{field.name!r}].count is {count}, not >= 1")
        fmt: Any = base.newbyteorder(order)
        if count != 1:
            fmt = (fmt, (count,))
        end = int(field.offset) + base.itemsize * count
        if end > point_step:
            raise LayoutError(
                f"point_cloud.fields[{field.name!r}] ends at byte {end}, beyond point_step "
                f"{point_step}"
            )
        if field.name in names:
            raise LayoutError(f"point_cloud.fields has {field.name!r} twice")
        names.append(field.name)
        formats.append(fmt)
        offsets.append(int(field.offset))
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )


def array_to_cloud(
    points: AnyArray,
    header: Any,
    is_bigendian: bool = False,
    point_step: int | None = None,
    is_dense: bool | None = None,
) -> Any:
    """(N,) structured array -> unorganised PointCloud2 (height 1, width N).

    Field offsets come from the array's dtype; ``point_step`` defaults to its itemsize and
    may be larger (zero padding). ``is_dense`` defaults to "x, y, z (if present) all
    finite".
    """
    pts = np.asarray(points)
    if pts.ndim != 1:
        raise LayoutError(f"points must have shape (N,), got {pts.shape}")
    fields = dtype_to_fields(pts.dtype)
    step = pts.dtype.itemsize if point_step is None else int(point_step)
    if step < pts.dtype.itemsize:
        raise LayoutError(f"point_step {step} is smaller than the point size {pts.dtype.itemsize}")
    wire = fields_to_dtype(fields, step, is_bigendian)
    buf = np.zeros(pts.shape[0], dtype=wire)
    for name in wire.names or ():
        buf[name] = pts[name]
    if is_dense is None:
        xyz = [n for n in ("x", "y", "z") if n in (wire.names or ())]
        is_dense = bool(all(np.isfinite(pts[n]).all() for n in xyz))
    msg = PointCloud2(header=header, height=1, width=int(pts.shape[0]), fields=fields)
    msg.is_bigendian = bool(is_bigendian)
    msg.point_step = step
    msg.row_step = step * int(pts.shape[0])
    msg.is_dense = is_dense
    msg.data = array.array("B", buf.tobytes())
    return msg


def cloud_to_array(msg: Any) -> AnyArray:
    """PointCloud2 -> (height * width,) structured array, native order, packed fields.

    Honours ``is_bigendian``, ``point_step`` and ``row_step`` padding, and any field order
    or offsets; fields with count > 1 become sub-arrays. Padding fields (PCL names them
    ``"_"``, possibly several times) and unnamed fields are skipped. The message is not
    modified.

    Raises:
        LayoutError: row_step < width * point_step, data length != row_step * height,
            unknown datatype, count < 1, a field beyond point_step, duplicated names.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if row_step < width * point_step:
        raise LayoutError(
            f"point_cloud.row_step {row_step} is smaller than width {width} * point_step "
            f"{point_step} = {width * point_step}"
        )
    fields = [f for f in msg.fields if str(f.name) not in _PADDING_NAMES]
    wire = fields_to_dtype(fields, point_step, msg.is_bigendian)
    buf = np.frombuffer(memoryview(msg.data).cast("B"), dtype=np.uint8)
    if buf.size != row_step * height:
        raise LayoutError(
            f"point_cloud.data has {buf.size} bytes, expected row_step {row_step} * height "
            f"{height} = {row_step * height}"
        )
    buf.flags.writeable = False
    rows = buf.reshape(height, row_step)[:, : width * point_step]
    wire_points = np.ascontiguousarray(rows).view(wire).reshape(-1)
    native = np.dtype(
        [(name, wire.fields[name][0].newbyteorder("=")) for name in wire.names or ()]  # type: ignore[index]
    )
    out = np.empty(wire_points.shape[0], dtype=native)
    for name in native.names or ():
        out[name] = wire_points[name]
    return out


def frame_result_to_cloud(
    result: FrameResult,
    header: Any,
    speed: float | None = None,
    is_bigendian: bool = False,
) -> Any:
    """FrameResult -> owl/points PointCloud2 with every OWL_FIELDS field (float32 unless noted).

    Args:
        result: the engine's output for one image (N points, N may be 0).
        header: the input image's header (frame_id = camera optical frame).
        speed: camera speed |t| in m/s from a speed source, or None. When given, x y z are
            ``points * speed`` (metres) and every point's ``speed`` field holds it; when
            None, x y z are in seconds and ``speed`` is NaN. Other fields never change unit.
        is_bigendian: byte order of the data.

    Raises:
        LayoutError: a per-point array whose shape does not match N.
        FieldError: speed not finite and positive.
    """
    n = result.num_points
    expected = {
        "pixels": (n, 2),
        "points": (n, 3),
        "omega": (n, 3),
        "rot": (n, 4),
        "range_over_speed": (n,),
        "quality": (n,),
        "ids": (n,),
        "flags": (n,),
    }
    for name, shape in expected.items():
        got = np.shape(getattr(result, name))
        if got != shape:
            raise LayoutError(f"FrameResult.{name} must have shape {shape}, got {got}")
    if speed is not None and not (np.isfinite(speed) and speed > 0):
        raise FieldError(f"speed must be finite and > 0 m/s, got {speed}")
    pts = np.zeros(n, dtype=OWL_DTYPE)
    xyz = np.asarray(result.points, dtype=np.float64)
    if speed is not None:
        xyz = xyz * float(speed)
    pts["x"], pts["y"], pts["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    pts["u"], pts["v"] = result.pixels[:, 0], result.pixels[:, 1]
    pts["L"] = result.looming
    pts["omega_x"], pts["omega_y"], pts["omega_z"] = result.omega.T
    pts["rot_w"], pts["rot_x"], pts["rot_y"], pts["rot_z"] = result.rot.T
    pts["range_over_speed"] = result.range_over_speed
    pts["quality"] = result.quality
    pts["speed"] = np.nan if speed is None else float(speed)
    pts["id"] = result.ids
    pts["flags"] = result.flags
    return array_to_cloud(pts, header, is_bigendian=is_bigendian)


def cloud_speed(points: AnyArray) -> float | None:
    """The speed (m/s) an OWL cloud was scaled with, or None when x y z are in seconds."""
    if points.dtype.names is None or "speed" not in points.dtype.names or points.size == 0:
        return None
    speeds = np.asarray(points["speed"], dtype=np.float64)
    finite = speeds[np.isfinite(speeds)]
    return float(finite[0]) if finite.size else None
