"""sensor_msgs/PointCloud2 <-> numpy without per-point Python loops.

Modelled on ``sensor_msgs_py.point_cloud2`` (not shipped in the PyPI wheels): a numpy structured
dtype is built from the message's fields (explicit offsets, ``itemsize = point_step``, the
message's byte order), so any field order, padding and extra fields are read as one view of
``data``. Messages of either flavour (rclpy or rosbags, see :mod:`msg_tools.msg_types`) are read
duck-typed; writers take the flavour to build.

A camera can send anything; :func:`validate_cloud` turns every inconsistency we can detect
(sizes, offsets, datatypes, x/y/z) into a :class:`CloudFormatError` that names the field, the
value and the fix, so the node can drop the frame with a useful warning.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from .msg_types import RCLPY, MessageTypes
from .palette import packed_rgb

__all__ = [
    "INT8", "UINT8", "INT16", "UINT16", "INT32", "UINT32", "FLOAT32", "FLOAT64",
    "DATATYPE_NAMES", "MAX_POINTS", "SEGMENTED_FIELDS", "SEGMENTED_DTYPE", "SEGMENTED_POINT_STEP",
    "CloudFormatError", "Field", "validate_cloud", "dtype_from_fields", "read_points", "read_xyz",
    "create_cloud", "create_segmented_cloud",
]

# sensor_msgs/PointField datatypes (Jazzy: 1..8).
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)

# datatype -> (name, numpy type code without byte order, size in bytes)
_DATATYPES: dict[int, tuple[str, str, int]] = {
    INT8: ("INT8", "i1", 1),
    UINT8: ("UINT8", "u1", 1),
    INT16: ("INT16", "i2", 2),
    UINT16: ("UINT16", "u2", 2),
    INT32: ("INT32", "i4", 4),
    UINT32: ("UINT32", "u4", 4),
    FLOAT32: ("FLOAT32", "f4", 4),
    FLOAT64: ("FLOAT64", "f8", 8),
}
DATATYPE_NAMES = {k: v[0] for k, v in _DATATYPES.items()}

MAX_POINTS = 50_000_000
"""More points than this in one message is treated as a corrupt header, not a real cloud."""

_XYZ = ("x", "y", "z")
_UINT32_LIMIT = 2**32


class CloudFormatError(ValueError):
    """A PointCloud2 we cannot read; the message names the field, the value and the fix.

    ``kind`` names the problem from a small fixed set (``"data_truncated"``, ``"missing_y"``...):
    the message text carries the publisher's numbers and field names, so it cannot key a
    warning throttle or a counter without growing with every distinct value.
    """

    def __init__(self, message: str, kind: str = "malformed"):
        super().__init__(message)
        self.kind = kind


class Field(NamedTuple):
    """A PointField of neither flavour (what :func:`create_cloud` accepts besides messages)."""

    name: str
    offset: int
    datatype: int
    count: int = 1


# Contract layout of ``segmented_points`` (DESIGN.md section 3): PCL's PointXYZRGBL by name,
# RViz2 (RGB8) and Foxglove (packed rgb) colour it without configuration.
SEGMENTED_FIELDS = (
    Field("x", 0, FLOAT32),
    Field("y", 4, FLOAT32),
    Field("z", 8, FLOAT32),
    Field("rgb", 12, FLOAT32),
    Field("label", 16, UINT32),
    Field("center_score", 20, FLOAT32),
)
SEGMENTED_POINT_STEP = 24
SEGMENTED_DTYPE = np.dtype(
    {
        "names": [f.name for f in SEGMENTED_FIELDS],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<f4"],
        "offsets": [f.offset for f in SEGMENTED_FIELDS],
        "itemsize": SEGMENTED_POINT_STEP,
    }
)
# Same bytes with rgb as uint32, so the packed colour is written bit-exactly.
_SEGMENTED_BUILD_DTYPE = np.dtype(
    {
        "names": [f.name for f in SEGMENTED_FIELDS],
        "formats": ["<f4", "<f4", "<f4", "<u4", "<u4", "<f4"],
        "offsets": [f.offset for f in SEGMENTED_FIELDS],
        "itemsize": SEGMENTED_POINT_STEP,
    }
)


def _dtname(datatype: int) -> str:
    name = DATATYPE_NAMES.get(int(datatype))
    return f"{name} ({datatype})" if name else f"{datatype}"


def _as_fields(fields: Sequence[Any]) -> list[Field]:
    """PointFields of either flavour, Field or plain tuples -> list[Field]."""
    out = []
    for f in fields:
        if isinstance(f, tuple):
            out.append(Field(*f))
        else:
            out.append(Field(str(f.name), int(f.offset), int(f.datatype), int(f.count)))
    return out


def validate_cloud(msg: Any, max_points: int = MAX_POINTS) -> None:
    """Raise :class:`CloudFormatError` unless ``msg`` is a PointCloud2 we can read x, y, z from.

    Checks dimensions (non-zero, not absurd), point_step, each field's datatype and extent,
    unique names, float x/y/z with count 1, row_step and the exact length of ``data``.
    """
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if height <= 0 or width <= 0:
        raise CloudFormatError(
            f"PointCloud2 has height {height} and width {width}: the cloud has no points; both "
            f"must be >= 1 (height 1 for an unorganized cloud)",
            kind="no_points",
        )
    n = height * width
    if n >= _UINT32_LIMIT or row_step * height >= _UINT32_LIMIT:
        raise CloudFormatError(
            f"PointCloud2 width*height = {width}*{height} = {n} points (row_step*height = "
            f"{row_step * height} bytes) overflows 32 bits (a CDR sequence holds < 2**32 bytes): the "
            f"header is corrupt; "
            f"check the publisher's width/height/row_step",
            kind="size_overflow",
        )
    if n > max_points:
        raise CloudFormatError(
            f"PointCloud2 width*height = {width}*{height} = {n} points exceeds the limit of "
            f"{max_points} (absurd dimensions); check the publisher's width/height, or raise max_points",
            kind="too_many_points",
        )
    if point_step <= 0:
        raise CloudFormatError(
            f"PointCloud2 point_step is {point_step}; it must be the byte size of one point "
            f"(at least the end of its last field)",
            kind="point_step",
        )
    fields = _as_fields(msg.fields)
    seen: dict[str, Field] = {}
    for f in fields:
        if f.name in seen:
            count = sum(1 for g in fields if g.name == f.name)
            raise CloudFormatError(
                f"PointCloud2 field name {f.name!r} appears {count} times (offsets "
                f"{[g.offset for g in fields if g.name == f.name]}); field names must be unique",
                kind="duplicate_field",
            )
        seen[f.name] = f
        if f.datatype not in _DATATYPES:
            raise CloudFormatError(
                f"PointCloud2 field {f.name!r} has unknown datatype {f.datatype}; "
                f"sensor_msgs/PointField datatypes are 1..8 (INT8, UINT8, INT16, UINT16, INT32, "
                f"UINT32, FLOAT32, FLOAT64)",
                kind="unknown_datatype",
            )
        if f.offset < 0 or f.count < 0:
            raise CloudFormatError(
                f"PointCloud2 field {f.name!r} has offset {f.offset} and count {f.count}; both must be >= 0",
                kind="negative_offset",
            )
        size = _DATATYPES[f.datatype][2]
        end = f.offset + size * f.count
        if end > point_step:
            raise CloudFormatError(
                f"PointCloud2 field {f.name!r} (offset {f.offset}, {_dtname(f.datatype)} x {f.count} = "
                f"{size * f.count} bytes) ends at byte {end} but point_step is {point_step}; point_step "
                f"must be >= {end} (or the field's offset is wrong)",
                kind="field_past_point_step",
            )
    for axis in _XYZ:
        f = seen.get(axis)
        if f is None:
            raise CloudFormatError(
                f"PointCloud2 has no field {axis!r} (fields: {', '.join(seen) or 'none'}); the cloud "
                f"needs x, y, z fields of datatype FLOAT32 (7) or FLOAT64 (8)",
                kind=f"missing_{axis}",
            )
        if f.datatype not in (FLOAT32, FLOAT64):
            raise CloudFormatError(
                f"PointCloud2 field {axis!r} has datatype {_dtname(f.datatype)}; x, y, z must be "
                f"FLOAT32 (7) or FLOAT64 (8) in metres: convert the coordinates to float before "
                f"publishing (e.g. depth_image_proc/point_cloud_xyz for depth images)",
                kind=f"{axis}_datatype",
            )
        if f.count != 1:
            raise CloudFormatError(
                f"PointCloud2 field {axis!r} has count {f.count}; x, y, z must each have count 1",
                kind=f"{axis}_count",
            )
    min_row = width * point_step
    if row_step < min_row:
        raise CloudFormatError(
            f"PointCloud2 row_step {row_step} < width*point_step = {width}*{point_step} = {min_row}; "
            f"row_step is the byte length of one row and must be at least width*point_step",
            kind="row_step",
        )
    expected = row_step * height
    have = len(msg.data)
    if have != expected:
        what = "truncated" if have < expected else "longer than its header says"
        raise CloudFormatError(
            f"PointCloud2 data has {have} bytes but row_step*height = {row_step}*{height} = "
            f"{expected}: the message is {what}; check the publisher's row_step/height/data",
            kind="data_truncated" if have < expected else "data_too_long",
        )


def dtype_from_fields(fields: Sequence[Any], point_step: int | None = None, is_bigendian: bool = False) -> np.dtype:
    """Structured dtype for one point: explicit offsets, ``itemsize = point_step``, message byte order.

    Fields with ``count > 1`` become subarrays. A field that cannot be represented (unknown
    datatype, count 0, duplicate name, past ``point_step``) is skipped, unless it is x, y or z,
    which raise :class:`CloudFormatError`.
    """
    order = ">" if is_bigendian else "<"
    fs = _as_fields(fields)
    if point_step is None:
        point_step = max((f.offset + _DATATYPES.get(f.datatype, ("", "", 0))[2] * f.count for f in fs), default=0)
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for f in fs:
        spec = _DATATYPES.get(f.datatype)
        problem = None
        if spec is None:
            problem = f"unknown datatype {f.datatype}"
        elif f.count < 1:
            problem = f"count {f.count}"
        elif f.name in names or not f.name:
            problem = "a duplicate or empty name"
        elif f.offset < 0 or f.offset + spec[2] * f.count > point_step:
            problem = f"offset {f.offset} + {spec[2] * f.count} bytes past point_step {point_step}"
        if problem:
            if f.name in _XYZ:
                raise CloudFormatError(f"PointCloud2 field {f.name!r} cannot be read: {problem}",
                                       kind="xyz_unreadable")
            continue
        assert spec is not None
        code = ("|" if spec[2] == 1 else order) + spec[1]
        names.append(f.name)
        formats.append(code if f.count == 1 else (code, (f.count,)))
        offsets.append(f.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(point_step)})


def _buffer(msg: Any) -> np.ndarray:
    """``msg.data`` as a flat uint8 array, zero-copy for array.array, bytes and numpy data."""
    data = msg.data
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:  # a list of ints
        return np.asarray(data, dtype=np.uint8)


def _strided(msg: Any, dtype: np.dtype) -> np.ndarray:
    """(height, width) view of the data with ``dtype``; honours row padding (row_step)."""
    height, width = int(msg.height), int(msg.width)
    return np.ndarray(
        shape=(height, width),
        dtype=dtype,
        buffer=_buffer(msg),
        strides=(int(msg.row_step), int(msg.point_step)),
    )


def read_points(msg: Any, *, validate: bool = True) -> np.ndarray:
    """Every point as a structured array of shape (height*width,), in message order.

    A zero-copy view of ``msg.data`` when rows are not padded (``row_step == width*point_step``),
    else a compact copy. Field names and types are the message's (native byte order is not
    forced; use ``.astype`` if you need it).
    """
    if validate:
        validate_cloud(msg)
    dtype = dtype_from_fields(msg.fields, int(msg.point_step), bool(msg.is_bigendian))
    grid = _strided(msg, dtype)
    if int(msg.row_step) == int(msg.width) * int(msg.point_step):
        return grid.reshape(-1)  # contiguous rows: still a view
    return np.ascontiguousarray(grid).reshape(-1)


def read_xyz(msg: Any, *, validate: bool = True) -> np.ndarray:
    """x, y, z as a C-contiguous float32 array (height*width, 3); NaN/Inf kept, order kept."""
    if validate:
        validate_cloud(msg)
    fields = {f.name: f for f in _as_fields(msg.fields)}
    order = ">" if msg.is_bigendian else "<"
    fx, fy, fz = (fields[a] for a in _XYZ)
    height, width = int(msg.height), int(msg.width)
    out = np.empty((height, width, 3), dtype=np.float32)
    native_f32 = order == ("<" if np.little_endian else ">") and fx.datatype == fy.datatype == fz.datatype == FLOAT32
    if native_f32 and fy.offset == fx.offset + 4 and fz.offset == fx.offset + 8:
        # Common camera layout: one strided (3,) float32 subarray per point, a single copy.
        dt = np.dtype({"names": ["xyz"], "formats": [(np.float32, (3,))], "offsets": [fx.offset],
                       "itemsize": int(msg.point_step)})
        np.copyto(out, _strided(msg, dt)["xyz"])
    else:
        dt = np.dtype({
            "names": list(_XYZ),
            "formats": [order + _DATATYPES[f.datatype][1] for f in (fx, fy, fz)],
            "offsets": [f.offset for f in (fx, fy, fz)],
            "itemsize": int(msg.point_step),
        })
        grid = _strided(msg, dt)
        for i, axis in enumerate(_XYZ):
            out[..., i] = grid[axis]  # casts float64 and byte-swaps in one pass
    return out.reshape(-1, 3)


def create_cloud(
    header: Any,
    fields: Sequence[Any],
    points: np.ndarray,
    types: MessageTypes = RCLPY,
    *,
    point_step: int | None = None,
    is_bigendian: bool = False,
    is_dense: bool = False,
) -> Any:
    """A PointCloud2 with ``fields`` (PointFields of either flavour, :class:`Field` or tuples).

    ``points`` is either a structured array with (at least) the fields' names, shape (N,) for
    an unorganized or (H, W) for an organized cloud, or a plain numeric array (N, C) / (H, W, C)
    whose C columns are the fields' values in order (a field with count k takes k columns).
    ``point_step`` defaults to the end of the last field; larger values pad each point.
    """
    fs = _as_fields(fields)
    if point_step is None:
        point_step = max((f.offset + _DATATYPES.get(f.datatype, ("", "", 0))[2] * f.count for f in fs), default=0)
    dtype = dtype_from_fields(fs, point_step, is_bigendian)
    if len(dtype.names or ()) != len(fs):
        lost = [f.name for f in fs if f.name not in (dtype.names or ())]
        raise CloudFormatError(f"cannot create PointCloud2: fields {lost} are not representable "
                               f"(unknown datatype, count < 1, duplicate name or past point_step {point_step})")
    pts = np.asarray(points)
    if pts.dtype.names is not None:
        if pts.ndim not in (1, 2):
            raise ValueError(f"structured points must have shape (N,) or (H, W), got {pts.shape}")
        shape = pts.shape
        missing = [f.name for f in fs if f.name not in pts.dtype.names]
        if missing:
            raise ValueError(f"points lack fields {missing} (have {list(pts.dtype.names)})")
        buf = np.zeros(shape, dtype=dtype)
        for f in fs:
            buf[f.name] = pts[f.name]
    else:
        if pts.ndim not in (2, 3):
            raise ValueError(f"numeric points must have shape (N, C) or (H, W, C), got {pts.shape}")
        columns = sum(f.count for f in fs)
        if pts.shape[-1] != columns:
            raise ValueError(
                f"points have {pts.shape[-1]} columns but fields {[f.name for f in fs]} need {columns}"
            )
        shape = pts.shape[:-1]
        buf = np.zeros(shape, dtype=dtype)
        col = 0
        for f in fs:
            buf[f.name] = pts[..., col] if f.count == 1 else pts[..., col:col + f.count]
            col += f.count
    height, width = (1, shape[0]) if len(shape) == 1 else shape
    return types.point_cloud2(
        header=header,
        height=height,
        width=width,
        fields=fs,
        is_bigendian=is_bigendian,
        point_step=point_step,
        row_step=point_step * width,
        data=buf.reshape(-1).view(np.uint8),
        is_dense=is_dense,
    )


def _packed_rgb_fast(labels: np.ndarray) -> np.ndarray:
    """:func:`packed_rgb` through a table over 0..max label (labels are small instance ids)."""
    top = int(labels.max()) if labels.size else 0
    if top >= 1 << 16:
        return packed_rgb(labels)
    return packed_rgb(np.arange(top + 1))[labels]


def create_segmented_cloud(
    header: Any,
    xyz: np.ndarray,
    labels: np.ndarray,
    center_score: np.ndarray | None,
    height: int,
    width: int,
    types: MessageTypes = RCLPY,
) -> Any:
    """The ``segmented_points`` cloud (DESIGN.md section 3), index-aligned with the input.

    x, y, z FLOAT32 at 0/4/8, rgb at 12 (palette colour packed 0x00RRGGBB, stored as the
    float32 with those bits), label UINT32 at 16 (0 = no instance), center_score FLOAT32 at 20;
    point_step 24, little-endian, ``is_dense`` false, the given height and width.
    """
    height, width = int(height), int(width)
    n = height * width
    xyz = np.asarray(xyz)
    labels = np.asarray(labels)
    if xyz.size != 3 * n or xyz.shape[-1] != 3:
        raise ValueError(f"xyz has shape {xyz.shape}; expected ({n}, 3) or ({height}, {width}, 3) "
                         f"for height {height} x width {width}")
    if labels.size != n:
        raise ValueError(f"labels has {labels.size} entries; expected height*width = {n}")
    if n and np.issubdtype(labels.dtype, np.signedinteger) and labels.min() < 0:
        raise ValueError(f"labels must be >= 0 (0 = no instance), got minimum {labels.min()}")
    score = None
    if center_score is not None:
        score = np.asarray(center_score)
        if score.size != n:
            raise ValueError(f"center_score has {score.size} entries; expected height*width = {n}")
    lab = labels.reshape(n)
    if np.little_endian:
        # Six 4-byte words per point written column by column straight into the message's
        # buffer: the structured-dtype writes of the same bytes were 3x slower on a 640x480
        # frame, and filling an array first cost two more 7.4 MB copies (into rclpy's
        # array.array, then its setter's own copy).
        data, raw = types.uint8_buffer(n * SEGMENTED_POINT_STEP)
        words = raw.view(np.float32).reshape(n, 6)
        bits = words.view(np.uint32)
        words[:, 0:3] = xyz.reshape(n, 3)
        bits[:, 3] = _packed_rgb_fast(lab)
        bits[:, 4] = lab
        words[:, 5] = 0.0 if score is None else score.reshape(n)
    else:  # pragma: no cover - big-endian hosts: explicit little-endian fields
        cloud = np.empty(n, dtype=_SEGMENTED_BUILD_DTYPE)
        flat = xyz.reshape(n, 3)
        cloud["x"], cloud["y"], cloud["z"] = flat[:, 0], flat[:, 1], flat[:, 2]
        cloud["rgb"] = packed_rgb(lab)
        cloud["label"] = lab
        cloud["center_score"] = 0.0 if score is None else score.reshape(n)
        data = cloud.view(np.uint8)
    return types.point_cloud2(
        header=header,
        height=height,
        width=width,
        fields=SEGMENTED_FIELDS,
        is_bigendian=False,
        point_step=SEGMENTED_POINT_STEP,
        row_step=SEGMENTED_POINT_STEP * width,
        data=data,
        is_dense=False,
    )
