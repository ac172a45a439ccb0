"""PointCloud2 <-> numpy against clouds packed by hand with struct (both message flavours)."""
from __future__ import annotations

import array
import math
import struct
import time

import numpy as np
import pytest

from msg_tools import point_cloud2 as pc
from msg_tools.msg_types import RCLPY, ROSBAGS, msgtype_of, stamp_ns, types_for
from msg_tools.palette import PALETTE

FLAVOURS = [pytest.param(RCLPY, id="rclpy"), pytest.param(ROSBAGS, id="rosbags")]
STRUCT = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}
SIZE = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
PAD = 0xAB  # garbage in padding bytes: reading it would show up as wrong values


def pack_cloud(types, fields, points, height, width, point_step, row_step, bigendian=False, frame="cam"):
    """Reference packer: one struct.pack per value, padding filled with garbage."""
    order = ">" if bigendian else "<"
    data = bytearray([PAD]) * (row_step * height)
    for idx, values in enumerate(points):
        r, c = divmod(idx, width)
        base = r * row_step + c * point_step
        for (name, offset, datatype, count) in fields:
            vals = values[name] if count > 1 else [values[name]]
            for k, v in enumerate(vals):
                struct.pack_into(order + STRUCT[datatype], data, base + offset + k * SIZE[datatype], v)
    return types.point_cloud2(
        header=types.header(frame, 12, 345),
        height=height,
        width=width,
        fields=[types.point_field(*f) for f in fields],
        is_bigendian=bigendian,
        point_step=point_step,
        row_step=row_step,
        data=bytes(data),
        is_dense=False,
    )


def sample_points(n, rng):
    pts = []
    for i in range(n):
        p = {
            "x": float(np.float32(rng.uniform(-2, 2))),
            "y": float(np.float32(rng.uniform(-2, 2))),
            "z": float(np.float32(rng.uniform(0, 3))),
            "intensity": float(np.float32(rng.uniform(0, 100))),
            "ring": int(rng.integers(0, 65535)),
            "rgb": float(np.float32(i)),
            "normal": [float(np.float32(v)) for v in rng.uniform(-1, 1, 3)],
        }
        pts.append(p)
    pts[1]["x"] = math.nan
    pts[2]["y"] = math.inf
    pts[3]["z"] = -math.inf
    return pts


def expected_xyz(points):
    return np.array([[p["x"], p["y"], p["z"]] for p in points], dtype=np.float32)


def padded_layout(xyz_type):
    """intensity first, xyz after a gap, then ring (uint16), rgb, a 3-vector; gaps everywhere."""
    s = SIZE[xyz_type]
    x0 = 6
    fields = [
        ("intensity", 0, pc.FLOAT32, 1),
        ("x", x0, xyz_type, 1),
        ("y", x0 + s + 2, xyz_type, 1),
        ("z", x0 + 2 * s + 4, xyz_type, 1),
        ("ring", x0 + 3 * s + 4, pc.UINT16, 1),
        ("rgb", x0 + 3 * s + 8, pc.FLOAT32, 1),
        ("normal", x0 + 3 * s + 12, pc.FLOAT32, 3),
    ]
    point_step = x0 + 3 * s + 12 + 12 + 5
    return fields, point_step


@pytest.mark.parametrize("types", FLAVOURS)
@pytest.mark.parametrize("xyz_type", [pc.FLOAT32, pc.FLOAT64], ids=["float32", "float64"])
@pytest.mark.parametrize("bigendian", [False, True], ids=["le", "be"])
@pytest.mark.parametrize("shape", [(3, 4), (1, 7)], ids=["organized", "unorganized"])
def test_round_trip_padded_layouts(types, xyz_type, bigendian, shape):
    rng = np.random.default_rng(1)
    height, width = shape
    fields, point_step = padded_layout(xyz_type)
    row_step = width * point_step + (9 if height > 1 else 0)  # row-end padding when organized
    pts = sample_points(height * width, rng)
    msg = pack_cloud(types, fields, pts, height, width, point_step, row_step, bigendian)

    xyz = pc.read_xyz(msg)
    assert xyz.dtype == np.float32 and xyz.shape == (height * width, 3) and xyz.flags.c_contiguous
    np.testing.assert_array_equal(xyz, expected_xyz(pts))  # NaN == NaN here, Inf kept
    assert np.isnan(xyz[1, 0]) and xyz[2, 1] == np.inf and xyz[3, 2] == -np.inf

    rec = pc.read_points(msg)
    assert rec.shape == (height * width,)
    np.testing.assert_array_equal(rec["ring"], [p["ring"] for p in pts])
    np.testing.assert_array_equal(rec["intensity"].astype(np.float32), [p["intensity"] for p in pts])
    np.testing.assert_array_equal(rec["rgb"].astype(np.float32), [p["rgb"] for p in pts])
    assert rec["normal"].shape == (height * width, 3)
    np.testing.assert_array_equal(rec["normal"].astype(np.float32), [p["normal"] for p in pts])
    np.testing.assert_array_equal(rec["x"].astype(np.float64), [p["x"] for p in pts])


@pytest.mark.parametrize("types", FLAVOURS)
def test_common_layout_is_zero_copy_and_fast_path(types):
    # PCL PointXYZI: x y z float32 at 0/4/8, intensity at 16, point_step 32
    fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 16, 7, 1)]
    rng = np.random.default_rng(2)
    pts = sample_points(6, rng)
    msg = pack_cloud(types, fields, pts, 2, 3, 32, 96)
    rec = pc.read_points(msg)
    assert np.shares_memory(rec, np.frombuffer(msg.data, dtype=np.uint8))
    np.testing.assert_array_equal(pc.read_xyz(msg), expected_xyz(pts))
    np.testing.assert_array_equal(rec["intensity"], np.float32([p["intensity"] for p in pts]))


@pytest.mark.parametrize("types", FLAVOURS)
def test_create_cloud_round_trip_numeric_and_structured(types):
    fields = [pc.Field("x", 0, pc.FLOAT32), pc.Field("y", 4, pc.FLOAT32), pc.Field("z", 8, pc.FLOAT32),
              pc.Field("ring", 12, pc.UINT16), pc.Field("t", 16, pc.FLOAT64)]
    values = np.array([[1.5, -2.0, 3.25, 7, 0.125], [np.nan, 0.0, 1.0, 65535, -1e300]])
    msg = pc.create_cloud(types.header("f", 1, 2), fields, values, types, point_step=32)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 2, 32, 64)
    assert len(msg.data) == 64
    raw = bytes(msg.data)
    for i, row in enumerate(values):
        x, y, z, ring, t = struct.unpack_from("<fffHxxd", raw, 32 * i)
        np.testing.assert_array_equal([x, y, z], np.float32(row[:3]))
        assert ring == int(row[3]) and t == row[4]
    # structured, organized
    rec = np.zeros((2, 3), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("ring", "u2"), ("t", "f8")])
    rec["x"] = np.arange(6).reshape(2, 3)
    rec["ring"] = 9
    msg2 = pc.create_cloud(types.header(), fields, rec, types)
    assert (msg2.height, msg2.width, msg2.point_step) == (2, 3, 24)
    back = pc.read_points(msg2)
    np.testing.assert_array_equal(back["x"], np.arange(6, dtype=np.float32))
    np.testing.assert_array_equal(back["ring"], 9)


@pytest.mark.parametrize("types", FLAVOURS)
def test_message_flavour(types):
    msg = pc.create_cloud(types.header("f", 1, 2), [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)],
                          np.zeros((4, 3)), types)
    assert types_for(msg) is types
    assert msgtype_of(msg) == "sensor_msgs/msg/PointCloud2"
    assert stamp_ns(msg.header) == 1_000_000_002
    if types is RCLPY:
        assert isinstance(msg.data, array.array) and msg.data.typecode == "B"
    else:
        assert isinstance(msg.data, np.ndarray) and msg.data.dtype == np.uint8


# -- segmented cloud: the contract's exact byte layout -------------------------------------------
@pytest.mark.parametrize("types", FLAVOURS)
def test_segmented_cloud_exact_bytes(types):
    height, width = 2, 3
    xyz = np.array([[0.1, 0.2, 0.3], [np.nan, np.nan, np.nan], [1, 2, 3],
                    [-1, -2, -3], [4, 5, 6], [7, 8, 9]], dtype=np.float32)
    labels = np.array([0, 0, 1, 2, 21, 5])
    score = np.array([0.0, 0.5, 1.0, 0.25, 0.75, 0.125], dtype=np.float32)
    header = RCLPY.header("camera_depth_optical_frame", 1700000000, 123456789)  # other flavour's header too
    msg = pc.create_segmented_cloud(header, xyz.reshape(2, 3, 3), labels.reshape(2, 3), score, height, width, types)

    assert msg.header.frame_id == "camera_depth_optical_frame"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1700000000, 123456789)
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (2, 3, 24, 72)
    assert msg.is_bigendian is False and msg.is_dense is False
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("rgb", 12, 7, 1), ("label", 16, 6, 1),
        ("center_score", 20, 7, 1)]
    raw = bytes(msg.data)
    assert len(raw) == 24 * 6

    def packed(label):
        if label == 0:
            return 0x808080
        r, g, b = (int(v) for v in PALETTE[(label - 1) % len(PALETTE)])
        return (r << 16) | (g << 8) | b

    assert packed(1) == 0xF3C300 and packed(21) == packed(1)
    for i in range(6):
        x, y, z, rgb_bits, label, s = struct.unpack_from("<fffIIf", raw, 24 * i)
        np.testing.assert_array_equal([x, y, z], xyz[i])
        assert rgb_bits == packed(int(labels[i]))
        assert label == labels[i]
        assert s == score[i]
    # the rgb field read as float32 carries the same bits (what RViz/PCL reinterpret)
    rgb_f = struct.unpack_from("<f", raw, 12 + 24 * 2)[0]
    assert struct.unpack("<I", struct.pack("<f", rgb_f))[0] == 0xF3C300
    # and it reads back through our own reader
    np.testing.assert_array_equal(pc.read_xyz(msg), xyz)
    pc.validate_cloud(msg)


@pytest.mark.parametrize("types", FLAVOURS)
def test_a_message_keeps_the_buffer_it_was_filled_in(types):
    """The segmented cloud is written once, into the message's own buffer: neither flavour's
    constructor nor rclpy's setter may copy it (7.4 MB per 640x480 frame each time)."""
    data, raw = types.uint8_buffer(48)
    raw[:] = np.arange(48, dtype=np.uint8)
    msg = types.point_cloud2(RCLPY.header(), 1, 2, [], False, 24, 48, data)
    assert msg.data is data if types is RCLPY else np.shares_memory(msg.data, raw)
    raw[0] = 200   # written after construction: the message sees it
    assert bytes(msg.data)[:2] == bytes([200, 1])
    image = types.compressed_image(data=data)
    assert image.data is data if types is RCLPY else np.shares_memory(image.data, raw)


def test_segmented_cloud_rejects_bad_shapes():
    with pytest.raises(ValueError, match="expected height\\*width = 6"):
        pc.create_segmented_cloud(ROSBAGS.header(), np.zeros((6, 3)), np.zeros(5, int), None, 2, 3, ROSBAGS)
    with pytest.raises(ValueError, match=r"expected \(4, 3\)"):
        pc.create_segmented_cloud(ROSBAGS.header(), np.zeros((6, 3)), np.zeros(4, int), None, 2, 2, ROSBAGS)
    with pytest.raises(ValueError, match="labels must be >= 0"):
        pc.create_segmented_cloud(ROSBAGS.header(), np.zeros((2, 3)), np.array([0, -1]), None, 1, 2, ROSBAGS)


# -- validation ---------------------------------------------------------------------------------
XYZ = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1)]


def raw_cloud(types, fields=XYZ, height=1, width=2, point_step=12, row_step=None, data_len=None):
    row_step = width * point_step if row_step is None else row_step
    n = row_step * height if data_len is None else data_len
    return types.point_cloud2(types.header(), height, width, [types.point_field(*f) for f in fields],
                              False, point_step, row_step, bytes(n), False)


@pytest.mark.parametrize("types", FLAVOURS)
@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(data_len=20), r"data has 20 bytes but row_step\*height = 24\*1 = 24.*truncated"),
        (dict(data_len=30), r"data has 30 bytes but row_step\*height = 24\*1 = 24.*longer"),
        (dict(point_step=10, row_step=24), r"field 'z' .*ends at byte 12 but point_step is 10"),
        (dict(point_step=0, row_step=0), r"point_step is 0"),
        (dict(fields=XYZ + [("rgb", 12, 7, 1)]), r"field 'rgb' .*ends at byte 16 but point_step is 12"),
        (dict(fields=XYZ[:2]), r"no field 'z' \(fields: x, y\)"),
        (dict(fields=[("x", 0, 5, 1), ("y", 4, 5, 1), ("z", 8, 5, 1)]), r"field 'x' has datatype INT32 \(5\)"),
        (dict(fields=XYZ[:2] + [("z", 8, 3, 1)]), r"field 'z' has datatype INT16 \(3\).*FLOAT32"),
        (dict(fields=XYZ + [("x", 0, 7, 1)]), r"field name 'x' appears 2 times"),
        (dict(fields=XYZ + [("w", 0, 42, 1)]), r"field 'w' has unknown datatype 42"),
        (dict(fields=[("x", 0, 7, 3)] + XYZ[1:]), r"field 'x' .*ends at byte 12|field 'x' has count 3"),
        (dict(height=0, data_len=0), r"height 0 and width 2.*no points"),
        (dict(width=0, data_len=0), r"height 1 and width 0"),
        (dict(row_step=20), r"row_step 20 < width\*point_step = 2\*12 = 24"),
    ],
)
def test_validation_errors(types, kwargs, pattern):
    msg = raw_cloud(types, **kwargs)
    with pytest.raises(pc.CloudFormatError, match=pattern):
        pc.validate_cloud(msg)
    with pytest.raises(pc.CloudFormatError):
        pc.read_xyz(msg)


def test_xyz_count_must_be_one():
    msg = raw_cloud(ROSBAGS, fields=[("x", 0, 7, 2), ("y", 8, 7, 1), ("z", 12, 7, 1)], point_step=16)
    with pytest.raises(pc.CloudFormatError, match="field 'x' has count 2"):
        pc.validate_cloud(msg)


class FakeCloud:
    """Header-only stand-in: a real message with these dimensions would need gigabytes."""

    def __init__(self, height, width, point_step=12, row_step=None):
        self.height, self.width, self.point_step = height, width, point_step
        self.row_step = width * point_step if row_step is None else row_step
        self.fields = [pc.Field(*f) for f in XYZ]
        self.is_bigendian = False
        self.data = b""


def test_absurd_and_overflowing_dimensions():
    with pytest.raises(pc.CloudFormatError, match=r"width\*height = 2147483648\*4 = 8589934592 .*overflows"):
        pc.validate_cloud(FakeCloud(4, 2**31))
    with pytest.raises(pc.CloudFormatError, match=r"exceeds the limit of 50000000"):
        pc.validate_cloud(FakeCloud(10000, 10000))
    with pytest.raises(pc.CloudFormatError, match="overflows"):
        pc.validate_cloud(FakeCloud(1000, 1000, point_step=12, row_step=2**30))
    # under the limit, only the data length is wrong
    with pytest.raises(pc.CloudFormatError, match="data has 0 bytes"):
        pc.validate_cloud(FakeCloud(480, 640))


def test_valid_cloud_passes_and_error_is_value_error():
    pc.validate_cloud(raw_cloud(ROSBAGS))
    assert issubclass(pc.CloudFormatError, ValueError)


def test_dtype_from_fields_skips_only_non_xyz():
    fields = XYZ + [("future", 12, 42, 1), ("empty", 12, 7, 0), ("far", 20, 7, 1)]
    dt = pc.dtype_from_fields([pc.Field(*f) for f in fields], 16, False)
    assert dt.names == ("x", "y", "z") and dt.itemsize == 16
    dt_be = pc.dtype_from_fields([pc.Field(*f) for f in XYZ] + [pc.Field("c", 12, 3, 2)], 16, True)
    assert dt_be["x"] == np.dtype(">f4") and dt_be["c"] == np.dtype((">i2", (2,)))
    assert dt_be.fields["c"][1] == 12
    with pytest.raises(pc.CloudFormatError, match="'z'"):
        pc.dtype_from_fields([pc.Field(*f) for f in XYZ[:2]] + [pc.Field("z", 8, 42, 1)], 16)


def test_read_xyz_is_fast_for_vga():
    rng = np.random.default_rng(0)
    n = 640 * 480
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    msg = pc.create_segmented_cloud(RCLPY.header(), xyz, np.zeros(n, int), None, 480, 640, RCLPY)
    best = min(_timed(pc.read_xyz, msg) for _ in range(3))
    np.testing.assert_array_equal(pc.read_xyz(msg), xyz)
    assert best < 0.05, f"read_xyz took {best * 1e3:.1f} ms for 640x480"
    f64 = pc.create_cloud(RCLPY.header(), [("x", 0, 8), ("y", 8, 8), ("z", 16, 8)],
                          xyz.astype(np.float64).reshape(480, 640, 3), RCLPY)
    assert min(_timed(pc.read_xyz, f64) for _ in range(3)) < 0.05
    np.testing.assert_array_equal(pc.read_xyz(f64), xyz)


def _timed(fn, *args):
    t = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t
