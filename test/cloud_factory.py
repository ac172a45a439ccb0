"""Valid and malformed PointCloud2 messages for the robustness tests and scripts, each kind named.

Shared by test/test_fuzz_node.py, test/test_node_faults.py, test/test_node_load.py,
test/test_bag_cli_errors.py and scripts/fuzz_node.py / scripts/load_node.py (which put test/ on
sys.path), so CI and the full runs send exactly the same catalogue.

* :func:`scene_xyz` renders a depth-camera view of a floor with spheres (a surface, like a real
  camera, not a volume of random points), NaN where there is no return.
* :func:`make_cloud` packs xyz into a PointCloud2 with one of several legal layouts (float32,
  float64, shuffled fields with extra fields and padding, big-endian, padded rows, unorganized).
* :data:`KINDS` is the mutation catalogue: every entry has a name, says whether the message is
  well-formed (the node must publish) or malformed (the node must drop it, with a warning
  containing ``warning``), and builds one message from a random generator.
* :func:`expected_valid` is an independent statement of the input contract (DESIGN.md section 3),
  written here from the message definition, not taken from msg_tools, so random header mutations
  can be classified without asking the code under test.
* :func:`check_output` checks a node's outputs for a valid input from first principles: the
  contract's fixed ``segmented_points`` layout is decoded with numpy here.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from msg_tools.msg_types import RCLPY, MessageTypes

# sensor_msgs/PointField datatypes (written out here on purpose: independent of msg_tools)
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
SIZES = {INT8: 1, UINT8: 1, INT16: 2, UINT16: 2, INT32: 4, UINT32: 4, FLOAT32: 4, FLOAT64: 8}
CODES = {INT8: "i1", UINT8: "u1", INT16: "i2", UINT16: "u2", INT32: "i4", UINT32: "u4",
         FLOAT32: "f4", FLOAT64: "f8"}
MAX_POINTS = 50_000_000          # DESIGN: more points than this is an absurd header
# The ROI the fuzzed node runs with: a real crop, but wide enough that huge-yet-finite
# coordinates (1e30) still reach the network; "outside the ROI" clouds sit beyond it.
FUZZ_ROI = ((-1e34, -1e34, -1e34), (1e34, 1e34, 1e34))

# The contract's segmented_points layout (DESIGN.md section 3), decoded independently.
SEGMENTED = np.dtype({"names": ["x", "y", "z", "rgb", "label", "center_score"],
                      "formats": ["<f4", "<f4", "<f4", "<u4", "<u4", "<f4"],
                      "offsets": [0, 4, 8, 12, 16, 20], "itemsize": 24})


# --------------------------------------------------------------------------- scenes and layouts

def scene_xyz(height: int, width: int, seed: int = 0, spheres: int = 12,
              radius: float = 0.04, nan_fraction: float = 0.03) -> np.ndarray:
    """(height, width, 3) float32: a pinhole camera 0.8 m above a floor, looking down on
    ``spheres`` balls of ``radius`` resting on it; ``nan_fraction`` of pixels have no return."""
    rng = np.random.default_rng(seed)
    f = 0.85 * width                       # ~60 degree horizontal field of view
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - width / 2) / f, (v - height / 2) / f, np.ones_like(u)], -1)
    floor = 0.8
    t = np.full((height, width), floor)    # ray z component is 1: t is the depth
    half = np.array([0.25 * width / f * floor * 2, 0.25 * height / f * floor * 2])
    centers = np.column_stack([rng.uniform(-half[0], half[0], spheres),
                               rng.uniform(-half[1], half[1], spheres),
                               np.full(spheres, floor - radius)])
    for c in centers:                      # analytic ray-sphere hits, nearest wins
        b = rays @ c
        rr = np.einsum("hwi,hwi->hw", rays, rays)
        disc = b * b - rr * (c @ c - radius * radius)
        hit = disc >= 0
        th = np.where(hit, (b - np.sqrt(np.where(hit, disc, 0))) / rr, np.inf)
        t = np.minimum(t, th)
    xyz = rays * t[..., None]
    xyz[rng.random((height, width)) < nan_fraction] = np.nan
    return xyz.astype(np.float32)


LAYOUTS = ("xyz32", "xyz64", "shuffled_padded", "bigendian", "row_padded", "unorganized",
           "mixed_float")


def make_cloud(xyz: np.ndarray, layout: str = "xyz32", stamp: int = 0, frame_id: str = "camera",
               types: MessageTypes = RCLPY) -> Any:
    """A well-formed PointCloud2 holding ``xyz`` ((H, W, 3) or (N, 3)) in ``layout``.

    ``stamp`` is the header stamp in nanoseconds. Every layout is legal per the contract (any
    float32/float64 x, y, z, any field order and padding, organized or not, either byte order).
    """
    xyz = np.asarray(xyz, np.float32)
    if xyz.ndim == 2 or layout == "unorganized":
        xyz = xyz.reshape(1, -1, 3)
    height, width = xyz.shape[:2]
    big = layout == "bigendian"
    order = ">" if big else "<"
    if layout in ("xyz32", "bigendian", "unorganized", "row_padded"):
        fields = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32)]
        point_step = 16
    elif layout == "xyz64":
        fields = [("x", 0, FLOAT64), ("y", 8, FLOAT64), ("z", 16, FLOAT64)]
        point_step = 24
    elif layout == "shuffled_padded":     # z first, extra fields, a hole, trailing padding
        fields = [("z", 0, FLOAT32), ("intensity", 4, FLOAT32), ("x", 12, FLOAT32),
                  ("rgb", 16, UINT32), ("y", 20, FLOAT32), ("ring", 24, UINT16)]
        point_step = 32
    elif layout == "mixed_float":
        fields = [("y", 0, FLOAT32), ("x", 4, FLOAT64), ("z", 12, FLOAT64), ("t", 20, UINT32)]
        point_step = 24
    else:
        raise ValueError(f"unknown layout {layout!r}; one of {LAYOUTS}")
    row_step = width * point_step + (12 if layout == "row_padded" else 0)
    dtype = np.dtype({"names": [f[0] for f in fields],
                      "formats": [order + CODES[f[2]] for f in fields],
                      "offsets": [f[1] for f in fields], "itemsize": point_step})
    rows = np.zeros((height, row_step), np.uint8)
    grid = np.zeros((height, width), dtype)
    for i, axis in enumerate("xyz"):
        grid[axis] = xyz[..., i]
    for name in grid.dtype.names:
        if name not in "xyz":
            grid[name] = 7
    rows[:, :width * point_step] = grid.view(np.uint8).reshape(height, -1)
    return types.point_cloud2(
        header=types.header(frame_id, stamp // 1_000_000_000, stamp % 1_000_000_000),
        height=height, width=width,
        fields=[types.point_field(n, o, d, 1) for n, o, d in fields],
        is_bigendian=big, point_step=point_step, row_step=row_step,
        data=rows.reshape(-1), is_dense=False)


def clone(msg: Any, **changes: Any) -> Any:
    """A copy of an rclpy PointCloud2 with some slots replaced (``fields`` as (name, offset,
    datatype, count) tuples or PointFields; ``data`` any bytes-like)."""
    cls = type(msg)
    out = cls()
    for slot in ("header", "height", "width", "fields", "is_bigendian", "point_step", "row_step",
                 "data", "is_dense"):
        value = changes.get(slot, getattr(msg, slot))
        if slot == "fields":
            value = [f if not isinstance(f, tuple) else RCLPY.point_field(*f) for f in value]
        if slot == "data":
            value = RCLPY.uint8(value)
        setattr(out, slot, value)
    return out


def fields_of(msg: Any) -> list[tuple[str, int, int, int]]:
    return [(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]


def set_stamp(msg: Any, stamp: int) -> Any:
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamp // 1_000_000_000, stamp % 1_000_000_000
    return msg


def stamp_of(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


# --------------------------------------------------------------------------- the contract, stated independently

def expected_valid(msg: Any) -> bool:
    """True when ``msg`` is well-formed per DESIGN.md section 3 (the node must segment it)."""
    h, w, ps, rs = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    if h < 1 or w < 1 or h * w > MAX_POINTS or ps < 1 or rs * h >= 2**32:
        return False
    fields = fields_of(msg)
    names = [f[0] for f in fields]
    if len(set(names)) != len(names):
        return False
    for _, off, dt, cnt in fields:
        if dt not in SIZES or off + SIZES[dt] * cnt > ps:
            return False
    by_name = {f[0]: f for f in fields}
    for axis in "xyz":
        if axis not in by_name or by_name[axis][2] not in (FLOAT32, FLOAT64) or by_name[axis][3] != 1:
            return False
    return rs >= w * ps and len(msg.data) == rs * h


def true_xyz(msg: Any) -> np.ndarray:
    """(N, 3) float32 decoded here with plain numpy (row by row), for checking outputs."""
    by_name = {f[0]: f for f in fields_of(msg)}
    order = ">" if msg.is_bigendian else "<"
    raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(int(msg.height), int(msg.row_step))
    raw = np.ascontiguousarray(raw[:, :int(msg.width) * int(msg.point_step)])
    pts = raw.reshape(int(msg.height) * int(msg.width), int(msg.point_step))
    out = np.empty((len(pts), 3), np.float32)
    for i, axis in enumerate("xyz"):
        _, off, dt, _ = by_name[axis]
        col = np.ascontiguousarray(pts[:, off:off + SIZES[dt]])
        out[:, i] = col.view(order + CODES[dt]).reshape(-1)
    return out


# --------------------------------------------------------------------------- the catalogue

@dataclass(frozen=True)
class Kind:
    """One named way to build a message. ``valid`` None: decided per message by expected_valid."""

    name: str
    valid: bool | None
    build: Callable[[np.random.Generator], Any]
    warning: str = ""             # malformed: a phrase the node's warning must contain
    zero_instances: bool = False  # well-formed but nothing to segment: all labels must be 0


def _small_scene(rng: np.random.Generator, layout: str | None = None) -> Any:
    h, w = int(rng.integers(8, 40)), int(rng.integers(8, 48))
    layout = layout or str(rng.choice(LAYOUTS))
    return make_cloud(scene_xyz(h, w, seed=int(rng.integers(1 << 30)), spheres=3), layout)


def _mutate_fields(fn):
    def build(r):
        msg = _small_scene(r, "shuffled_padded" if r.random() < 0.5 else "xyz32")
        return fn(r, msg, fields_of(msg))
    return build


def _replace_field(fields, name, **kw):
    out = []
    for f in fields:
        if f[0] == name:
            f = (kw.get("name", f[0]), kw.get("offset", f[1]), kw.get("datatype", f[2]),
                 kw.get("count", f[3]))
        out.append(f)
    return out


def _xyz_as(datatype: int, size: int):
    """x, y, z stored as integers / half floats, fields saying so."""
    def build(r):
        h, w = int(r.integers(4, 20)), int(r.integers(4, 20))
        xyz = scene_xyz(h, w, seed=int(r.integers(1 << 30)), spheres=2)
        if datatype in CODES and CODES[datatype][0] in "iu":
            vals = np.nan_to_num(xyz * 1000).astype("<" + CODES[datatype])   # millimetres
        else:
            vals = xyz.astype("<f2")
        data = vals.reshape(h, w, 3).view(np.uint8).reshape(-1)
        fields = [("x", 0, datatype, 1), ("y", size, datatype, 1), ("z", 2 * size, datatype, 1)]
        base = make_cloud(xyz)
        return clone(base, fields=fields, point_step=3 * size, row_step=3 * size * w, data=data)
    return build


def _truncate(r, m):
    n = len(m.data)
    return clone(m, data=bytes(m.data)[:int(r.integers(0, n))])


def _extend(r, m):
    return clone(m, data=bytes(m.data) + bytes(int(r.integers(1, 2000))))


def _point_step_small(r, m):
    end = max(f[1] + SIZES[f[2]] * f[3] for f in fields_of(m))
    ps = int(r.integers(1, end))
    return clone(m, point_step=ps, row_step=ps * m.width, data=bytes(ps * m.width * m.height))


def _offset_past(r, m):
    fields = fields_of(m)
    name = fields[int(r.integers(len(fields)))][0]
    f = [g for g in fields if g[0] == name][0]
    off = int(m.point_step) - SIZES[f[2]] + int(r.integers(1, 64))
    return clone(m, fields=_replace_field(fields, name, offset=off))


def _overflow(r, m):
    w = int(r.integers(1 << 16, 1 << 20))
    h = int(np.ceil(2**32 / w)) + int(r.integers(0, 100))
    return clone(m, width=w, height=h, row_step=w * int(m.point_step))


def _row_step_overflow(r, m):
    return clone(m, height=2, width=1, row_step=2**31 + int(r.integers(0, 1 << 20)))


def _absurd(r, m):
    w = int(r.integers(60_000, 100_000))
    return clone(m, width=w, height=1000, row_step=w * 4, point_step=4,
                 fields=[("x", 0, FLOAT32, 1), ("y", 0, FLOAT32, 1), ("z", 0, FLOAT32, 1)])


def _row_step_small(r, m):
    rs = int(r.integers(0, m.width * m.point_step))
    return clone(m, row_step=rs, data=bytes(rs * m.height))


def _header_chaos(r, m):
    """Random header/field edits; validity decided by :func:`expected_valid`."""
    changes: dict[str, Any] = {}
    fields = fields_of(m)
    for _ in range(int(r.integers(1, 4))):
        what = int(r.integers(7))
        if what == 0:
            changes["height"] = int(r.choice([0, 1, m.height, m.height + 1, int(r.integers(0, 1 << 32))]))
        elif what == 1:
            changes["width"] = int(r.choice([0, 1, m.width, m.width - 1, int(r.integers(0, 1 << 32))]))
        elif what == 2:
            changes["point_step"] = int(r.choice([0, 1, m.point_step - 1, m.point_step + 4,
                                                  int(r.integers(0, 1 << 32))]))
        elif what == 3:
            changes["row_step"] = int(r.choice([0, m.row_step - 1, m.row_step + 1, int(r.integers(0, 1 << 32))]))
        elif what == 4:
            i = int(r.integers(len(fields)))
            name, off, dt, cnt = fields[i]
            fields[i] = (name, int(r.choice([off, off + 1, off + 64, int(r.integers(0, 1 << 32))])),
                         int(r.choice([dt, int(r.integers(0, 256))])),
                         int(r.choice([cnt, 0, 2, int(r.integers(0, 1 << 32))])))
            changes["fields"] = fields
        elif what == 5:
            data = bytes(m.data)
            cut = int(r.integers(0, len(data) + 1))
            changes["data"] = data[:cut] if r.random() < 0.5 else data + bytes(cut)
        else:
            i = int(r.integers(len(fields)))
            fields[i] = (str(r.choice(["x", "y", "z", "", "X", "rgb", "x" * 300])),) + fields[i][1:]
            changes["fields"] = fields
    return clone(m, **changes)


def _byte_flips(r):
    m = _small_scene(r, "xyz32")
    data = np.frombuffer(bytes(m.data), np.uint8).copy()
    idx = r.integers(0, len(data), max(1, len(data) // 50))
    data[idx] ^= r.integers(1, 256, len(idx)).astype(np.uint8)
    return clone(m, data=data)


def _fill(values):
    def build(r):
        h, w = int(r.integers(2, 30)), int(r.integers(2, 30))
        xyz = r.choice(np.asarray(values, np.float32), size=(h, w, 3))
        return make_cloud(xyz, str(r.choice(LAYOUTS)))
    return build


def _outside_roi(r):
    xyz = scene_xyz(int(r.integers(8, 40)), int(r.integers(8, 40)), seed=int(r.integers(1 << 30)))
    xyz[..., int(r.integers(3))] += FUZZ_ROI[1][0] * float(r.uniform(1.5, 100))  # beyond the box
    return make_cloud(xyz, str(r.choice(LAYOUTS)))


def _single_point(r):
    return make_cloud(np.array([[[0.01, -0.02, 0.75]]], np.float32), str(r.choice(LAYOUTS)))


def _huge_coordinates(r):
    xyz = (r.uniform(-1, 1, (int(r.integers(2, 30)), int(r.integers(2, 30)), 3)) * 1e30)
    return make_cloud(xyz.astype(np.float32), "xyz32")


def two_million_points(r: np.random.Generator | None = None) -> Any:
    """A 1600 x 1250 (2,000,000 point) organized depth-camera cloud, ~32 MB."""
    seed = int(r.integers(1 << 30)) if r is not None else 0
    return make_cloud(scene_xyz(1250, 1600, seed=seed, spheres=40), "xyz32")


CANARY_SHAPE = (24, 32)


def canary() -> Any:
    """The same valid cloud every time: its outputs must not change over a run."""
    return make_cloud(scene_xyz(*CANARY_SHAPE, seed=12345, spheres=4), "shuffled_padded")


KINDS: tuple[Kind, ...] = (
    # ---- malformed: dropped, nothing published, a warning containing `warning`
    Kind("data_shorter_than_row_step_x_height", False,
         lambda r: _truncate(r, _small_scene(r)), "truncated"),
    Kind("data_longer_than_row_step_x_height", False,
         lambda r: _extend(r, _small_scene(r)), "longer than its header says"),
    Kind("point_step_smaller_than_fields", False,
         lambda r: _point_step_small(r, _small_scene(r)), "point_step"),
    Kind("point_step_zero", False,
         lambda r: clone(_small_scene(r), point_step=0), "point_step is 0"),
    Kind("field_offset_past_point_step", False,
         lambda r: _offset_past(r, _small_scene(r)), "but point_step is"),
    Kind("width_x_height_overflows_32_bits", False,
         lambda r: _overflow(r, _small_scene(r)), "overflows 32 bits"),
    Kind("row_step_x_height_overflows_32_bits", False,
         lambda r: _row_step_overflow(r, _small_scene(r)), "overflows 32 bits"),
    Kind("absurd_dimensions_60M_points", False,
         lambda r: _absurd(r, _small_scene(r)), "exceeds the limit"),
    Kind("row_step_smaller_than_width_x_point_step", False,
         lambda r: _row_step_small(r, _small_scene(r)), "row_step"),
    Kind("height_0", False, lambda r: clone(_small_scene(r), height=0, data=b""), "no points"),
    Kind("width_0", False, lambda r: clone(_small_scene(r), width=0, row_step=0, data=b""),
         "no points"),
    Kind("height_0_width_0_with_data", False,
         lambda r: clone(_small_scene(r), height=0, width=0), "no points"),
    Kind("missing_x", False, _mutate_fields(lambda r, m, f: clone(
        m, fields=[g for g in f if g[0] != "x"])), "no field 'x'"),
    Kind("missing_y", False, _mutate_fields(lambda r, m, f: clone(
        m, fields=[g for g in f if g[0] != "y"])), "no field 'y'"),
    Kind("missing_z", False, _mutate_fields(lambda r, m, f: clone(
        m, fields=[g for g in f if g[0] != "z"])), "no field 'z'"),
    Kind("no_fields", False, lambda r: clone(_small_scene(r), fields=[]), "no field 'x'"),
    Kind("duplicated_x", False, _mutate_fields(lambda r, m, f: clone(
        m, fields=f + [("x", 0, FLOAT32, 1)])), "appears 2 times"),
    Kind("duplicated_extra_field", False, lambda r: (lambda m: clone(
        m, fields=fields_of(m) + [("intensity", 8, FLOAT32, 1)]))(
        _small_scene(r, "shuffled_padded")), "appears 2 times"),
    Kind("xyz_int16_millimetres", False, _xyz_as(INT16, 2), "must be FLOAT32 (7) or FLOAT64 (8)"),
    Kind("xyz_int32_millimetres", False, _xyz_as(INT32, 4), "must be FLOAT32 (7) or FLOAT64 (8)"),
    Kind("xyz_uint16_millimetres", False, _xyz_as(UINT16, 2), "must be FLOAT32 (7) or FLOAT64 (8)"),
    Kind("xyz_float16_datatype_9", False, _xyz_as(9, 2), "unknown datatype 9"),
    Kind("extra_field_unknown_datatype", False, _mutate_fields(lambda r, m, f: clone(
        m, fields=f + [("weird", 0, int(r.choice([0, 9, 42, 255])), 1)])), "unknown datatype"),
    Kind("xyz_count_0", False, _mutate_fields(lambda r, m, f: clone(
        m, fields=_replace_field(f, str(r.choice(["x", "y", "z"])), count=0))), "must each have count 1"),
    Kind("xyz_count_3", False, lambda r: (lambda m: clone(
        m, fields=_replace_field(fields_of(m), "x", count=3)))(_small_scene(r, "xyz32")),
        "must each have count 1"),  # the problem, not the value: random
    # header edits share its throttle key and may be the one warned about within the 5 s window
    # ---- random header edits: validity per message from expected_valid()
    Kind("random_header_edits", None, lambda r: _header_chaos(r, _small_scene(r))),
    # ---- well-formed: the node must publish, correctly
    *(Kind(f"scene_{layout}", True, (lambda lay: lambda r: _small_scene(r, lay))(layout))
      for layout in LAYOUTS),
    Kind("random_byte_flips", True, _byte_flips),
    Kind("nan_everywhere", True, _fill([np.nan]), zero_instances=True),
    Kind("nan_inf_everywhere", True, _fill([np.nan, np.inf, -np.inf]), zero_instances=True),
    Kind("every_point_outside_roi", True, _outside_roi, zero_instances=True),
    Kind("single_point", True, _single_point, zero_instances=True),
    Kind("huge_finite_coordinates", True, _huge_coordinates),
)
BY_NAME = {k.name: k for k in KINDS}
TWO_MILLION = Kind("two_million_points", True, two_million_points)


# --------------------------------------------------------------------------- output checks

def decode_segmented(out: Any) -> np.ndarray:
    """The contract layout of segmented_points as a structured (N,) array (checks the header)."""
    assert [(f.name, f.offset, f.datatype, f.count) for f in out.fields] == [
        ("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1), ("z", 8, FLOAT32, 1), ("rgb", 12, FLOAT32, 1),
        ("label", 16, UINT32, 1), ("center_score", 20, FLOAT32, 1)], out.fields
    assert out.point_step == 24 and not out.is_bigendian
    assert out.row_step == 24 * out.width and len(out.data) == out.row_step * out.height
    return np.frombuffer(bytes(out.data), SEGMENTED)


def check_output(inp: Any, outputs: dict[str, Any], kind: Kind,
                 roi: tuple | None = FUZZ_ROI) -> np.ndarray:
    """Assert the three outputs are a correct answer for ``inp``; returns the labels.

    Correct, from the contract alone: same header; same height, width and point order; xyz
    copied; label 0 wherever xyz is not finite or outside the ROI; labels 1..K with one pose per
    label at the mean of its points; markers a DELETEALL plus a sphere and a text per instance.
    """
    cloud, poses, markers = (outputs["segmented_points"], outputs["instances"],
                             outputs["instance_markers"])
    for msg in (cloud, poses):
        assert stamp_of(msg) == stamp_of(inp) and msg.header.frame_id == inp.header.frame_id
    assert (cloud.height, cloud.width) == (inp.height, inp.width)
    pts = decode_segmented(cloud)
    xyz = true_xyz(inp)
    got = np.column_stack([pts["x"], pts["y"], pts["z"]])
    np.testing.assert_array_equal(got, xyz)   # NaN positions compare equal
    labels = pts["label"]
    usable = np.isfinite(xyz).all(axis=1)
    if roi is not None:
        with np.errstate(invalid="ignore"):
            usable &= ((xyz >= roi[0]) & (xyz <= roi[1])).all(axis=1)
    assert not labels[~usable].any(), "labels on non-finite or out-of-ROI points"
    k = len(poses.poses)
    assert sorted(set(labels[labels > 0].tolist())) == list(range(1, k + 1))
    if kind.zero_instances:
        assert k == 0 and not labels.any()
    for i, pose in enumerate(poses.poses):
        mean = xyz[labels == i + 1].astype(np.float64).mean(axis=0)
        np.testing.assert_allclose([pose.position.x, pose.position.y, pose.position.z], mean,
                                   rtol=1e-5, atol=1e-4)
    ms = markers.markers
    assert ms and ms[0].action == 3, "markers must start with DELETEALL"
    finite = sum(np.isfinite([p.position.x, p.position.y, p.position.z]).all() for p in poses.poses)
    assert len(ms) == 1 + 2 * finite   # a sphere and a text per instance (RViz rejects NaN poses)
    for m in ms:
        assert stamp_of(m) == stamp_of(inp) and m.header.frame_id == inp.header.frame_id
    return labels
