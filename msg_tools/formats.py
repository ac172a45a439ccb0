"""Scene files <-> numpy: NPZ (DESIGN.md section 4), the paper's text format, PLY and PCD.

Every reader returns ``(xyz, extra)``: ``xyz`` float32 with shape (N, 3), or (H, W, 3) for an
organized source (NPZ stored that way, PCD with HEIGHT > 1), NaN kept; ``extra`` maps the
file's other per-point fields (same leading shape) and scalars (NPZ) by name. Readers are
vectorised (np.loadtxt / np.frombuffer), so a 640x480 scene loads in well under a second.
"""
from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .palette import label_colors

__all__ = [
    "FormatError", "PAPER_COLUMNS", "PEER_COLUMNS", "SCENE_EXTENSIONS",
    "read_scene", "read_npz", "read_txt", "read_ply", "read_pcd", "write_npz", "write_ply",
]

PAPER_COLUMNS = ("x", "y", "z", "center_score", "instance")
"""The FPCC paper's text scenes: ``x y z center_score instance`` per line."""
PEER_COLUMNS = ("x", "y", "z", "instance", "center_score")
"""The peer tool's text scenes: ``x y z instance center_score`` per line."""
_NAMED_COLUMNS = {"paper": PAPER_COLUMNS, "peer": PEER_COLUMNS}
SCENE_EXTENSIONS = (".npz", ".txt", ".ply", ".pcd")


class FormatError(ValueError):
    """A scene file we cannot read or write; names the file, the problem and the fix."""


def read_scene(path: str | os.PathLike[str], *, columns: Sequence[str] | str | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Read any supported scene file by its extension (.npz, .txt, .ply, .pcd).

    ``columns`` applies to .txt only: a sequence of names or ``"paper"`` (default) / ``"peer"``.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext != ".txt" and columns is not None:
        raise FormatError(f"columns= applies to .txt scenes only, not {path.name!r}")
    if not path.is_file():
        raise FormatError(f"scene file {str(path)!r} does not exist")
    if ext == ".npz":
        return read_npz(path)
    if ext == ".txt":
        return read_txt(path, columns=PAPER_COLUMNS if columns is None else columns)
    if ext == ".ply":
        return read_ply(path)
    if ext == ".pcd":
        return read_pcd(path)
    raise FormatError(
        f"unsupported scene file extension {ext or '(none)'!r} for {str(path)!r}; supported: "
        f"{', '.join(SCENE_EXTENSIONS)} (rosbag2 directories and .mcap go through msg_tools.bag)"
    )


# -- NPZ ------------------------------------------------------------------------------------------
def read_npz(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """DESIGN.md section 4 scene: ``points`` plus every other key (0-d arrays become scalars)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as err:
        raise FormatError(f"cannot read NPZ {str(path)!r}: {err}") from err
    if "points" not in arrays:
        raise FormatError(f"NPZ {str(path)!r} has no 'points' array (keys: {sorted(arrays)}); a scene needs "
                          f"'points' float32 (N,3) or (H,W,3) in metres")
    points = arrays.pop("points")
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise FormatError(f"NPZ {str(path)!r}: 'points' has shape {points.shape}; expected (N,3) or (H,W,3)")
    lead = points.shape[:-1]
    extra: dict[str, Any] = {}
    for key, value in arrays.items():
        if value.ndim == 0:
            extra[key] = value.item()
            continue
        if key in ("instance", "center_score") and value.shape != lead:
            raise FormatError(f"NPZ {str(path)!r}: {key!r} has shape {value.shape} but points lead with "
                              f"{lead}; they must match point for point")
        extra[key] = value
    if "instance" in extra:
        extra["instance"] = extra["instance"].astype(np.int32, copy=False)
    if "center_score" in extra:
        extra["center_score"] = extra["center_score"].astype(np.float32, copy=False)
    return points.astype(np.float32, copy=False), extra


def write_npz(
    path: str | os.PathLike[str],
    points: np.ndarray,
    instance: np.ndarray | None = None,
    center_score: np.ndarray | None = None,
    part_radius: float | None = None,
    **extra: Any,
) -> None:
    """Write a DESIGN.md section 4 scene (compressed); written to a temp file, then renamed."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim not in (2, 3) or pts.shape[-1] != 3:
        raise FormatError(f"points must have shape (N,3) or (H,W,3), got {pts.shape}")
    arrays: dict[str, Any] = {"points": pts}
    lead = pts.shape[:-1]
    for key, value, dtype in (("instance", instance, np.int32), ("center_score", center_score, np.float32)):
        if value is None:
            continue
        arr = np.asarray(value, dtype=dtype)
        if arr.size != int(np.prod(lead)):
            raise FormatError(f"{key} has {arr.size} entries but points has {int(np.prod(lead))}")
        arrays[key] = arr.reshape(lead)
    if part_radius is not None:
        arrays["part_radius"] = np.float32(part_radius)
    arrays.update(extra)
    _atomic_write(Path(path), lambda f: np.savez_compressed(f, **arrays))


def _atomic_write(path: Path, write: Any) -> None:
    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


# -- paper text format ----------------------------------------------------------------------------
def read_txt(path: str | os.PathLike[str], columns: Sequence[str] | str = PAPER_COLUMNS) -> tuple[np.ndarray, dict[str, Any]]:
    """Whitespace- or comma-separated rows; ``columns`` names them (``"paper"`` or ``"peer"`` too).

    A file may have fewer columns than named (e.g. just x y z); ``instance`` becomes int32,
    every other column float32. Lines starting with ``#`` are comments.
    """
    names = _NAMED_COLUMNS.get(columns, None) if isinstance(columns, str) else tuple(columns)
    if names is None:
        raise FormatError(f"unknown columns preset {columns!r}; use 'paper' {PAPER_COLUMNS}, 'peer' "
                          f"{PEER_COLUMNS} or a list of names")
    if tuple(names[:3]) != ("x", "y", "z") or len(set(names)) != len(names):
        raise FormatError(f"columns must start with x, y, z and be unique, got {tuple(names)}")
    first = _first_data_line(path)
    delimiter = "," if first is not None and "," in first else None
    try:
        data = np.loadtxt(path, comments="#", delimiter=delimiter, ndmin=2, dtype=np.float64)
    except ValueError as err:
        raise FormatError(f"cannot parse text scene {str(path)!r}: {err}") from err
    if data.size == 0:
        return np.zeros((0, 3), np.float32), {}
    ncols = data.shape[1]
    if ncols < 3 or ncols > len(names):
        raise FormatError(
            f"text scene {str(path)!r} has {ncols} columns but columns={tuple(names)} names {len(names)}; "
            f"need 3..{len(names)} (pass columns= to name them, e.g. 'peer' for x y z instance center_score)"
        )
    extra: dict[str, Any] = {}
    for i, name in enumerate(names[3:ncols], start=3):
        col = data[:, i]
        extra[name] = np.rint(col).astype(np.int32) if name in ("instance", "label") else col.astype(np.float32)
    return np.ascontiguousarray(data[:, :3], dtype=np.float32), extra


def _first_data_line(path: str | os.PathLike[str]) -> str | None:
    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            s = line.strip()
            if s and not s.startswith("#"):
                return s
    return None


# -- PLY ------------------------------------------------------------------------------------------
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _read_header(f: io.BufferedReader, path: Any, first: bytes, end: bytes, limit: int = 200) -> list[str]:
    """Header lines up to and including the one starting with ``end``; f is left after it."""
    lines = []
    for _ in range(limit):
        raw = f.readline()
        if not raw:
            raise FormatError(f"{str(path)!r}: file ends inside the header (no {end.decode()!r} line)")
        line = raw.decode("ascii", errors="replace").strip()
        lines.append(line)
        if not lines[0].startswith(first.decode()):
            raise FormatError(f"{str(path)!r} does not start with {first.decode()!r}; not a "
                              f"{'PLY' if first == b'ply' else 'PCD'} file")
        if raw.startswith(end):
            return lines
    raise FormatError(f"{str(path)!r}: no {end.decode()!r} within {limit} header lines")


def read_ply(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """ASCII or binary (little/big endian) PLY: the vertex element's x, y, z plus its other scalar
    properties (e.g. ``label``, ``center_score``, ``red``/``green``/``blue``) in ``extra``."""
    with open(path, "rb") as f:
        header = _read_header(f, path, b"ply", b"end_header")
        body_offset = f.tell()
        fmt = None
        elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []
        for line in header[1:]:
            tok = line.split()
            if not tok or tok[0] in ("comment", "obj_info", "end_header"):
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element":
                elements.append((tok[1], int(tok[2]), []))
            elif tok[0] == "property":
                if not elements:
                    raise FormatError(f"PLY {str(path)!r}: property before any element")
                if tok[1] == "list":
                    elements[-1][2].append((tok[4], None))
                else:
                    if tok[1] not in _PLY_TYPES:
                        raise FormatError(f"PLY {str(path)!r}: unknown property type {tok[1]!r} for {tok[2]!r}")
                    elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
        if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
            raise FormatError(f"PLY {str(path)!r}: unsupported format {fmt!r} (ascii, binary_little_endian, "
                              f"binary_big_endian)")
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise FormatError(f"PLY {str(path)!r} has no vertex element (elements: {names})")
        vi = names.index("vertex")
        _, count, props = elements[vi]
        if any(t is None for _, t in props):
            raise FormatError(f"PLY {str(path)!r}: list properties in the vertex element are not supported")
        prop_names = [n for n, _ in props]
        for axis in "xyz":
            if axis not in prop_names:
                raise FormatError(f"PLY {str(path)!r}: vertex element has no {axis!r} property "
                                  f"(properties: {prop_names})")
        if fmt == "ascii":
            skip = sum(e[1] for e in elements[:vi])
            text = f.read().decode("ascii", errors="replace").splitlines()
            rows = text[skip:skip + count]
            if len(rows) < count:
                raise FormatError(f"PLY {str(path)!r}: header says {count} vertices, file has {len(rows)} rows")
            table = np.loadtxt(rows, dtype=np.float64, ndmin=2) if count else np.zeros((0, len(props)))
            if table.shape[1] != len(props):
                raise FormatError(f"PLY {str(path)!r}: vertex rows have {table.shape[1]} values, header "
                                  f"declares {len(props)} properties")
            columns = {n: table[:, i].astype(t) for i, (n, t) in enumerate(props)}
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            skip_bytes = 0
            for name, n, eprops in elements[:vi]:
                if any(t is None for _, t in eprops):
                    raise FormatError(f"PLY {str(path)!r}: element {name!r} before vertex has list "
                                      f"properties; only the vertex element may come first then")
                skip_bytes += n * sum(np.dtype(t).itemsize for _, t in eprops)  # type: ignore[arg-type]
            dt = np.dtype([(n, order + t) for n, t in props])  # type: ignore[operator]
            f.seek(body_offset + skip_bytes)
            buf = f.read(dt.itemsize * count)
            if len(buf) < dt.itemsize * count:
                raise FormatError(f"PLY {str(path)!r} is truncated: {count} vertices need "
                                  f"{dt.itemsize * count} bytes, file has {len(buf)}")
            table = np.frombuffer(buf, dtype=dt, count=count)
            columns = {n: table[n].astype(table[n].dtype.newbyteorder("=")) for n in prop_names}
    xyz = np.stack([columns.pop(a).astype(np.float32) for a in "xyz"], axis=1)
    return xyz, columns


def write_ply(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    labels: np.ndarray | None = None,
    center_score: np.ndarray | None = None,
    *,
    binary: bool = True,
) -> None:
    """PLY of every point (organized input is flattened row-major, NaN kept) with palette colours
    (red/green/blue), ``label`` (uint32) and ``center_score`` (float) properties when given;
    opens in MeshLab/CloudCompare. Written to a temp file, then renamed."""
    pts = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    n = len(pts)
    fields: list[tuple[str, str, str]] = [("x", "<f4", "float"), ("y", "<f4", "float"), ("z", "<f4", "float")]
    values: dict[str, np.ndarray] = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2]}
    if labels is not None:
        lab = np.asarray(labels).reshape(-1)
        if lab.size != n:
            raise FormatError(f"labels has {lab.size} entries but xyz has {n} points")
        if lab.size and lab.min() < 0:
            raise FormatError(f"labels must be >= 0 (0 = no instance), got minimum {lab.min()}")
        rgb = label_colors(lab)
        for i, c in enumerate(("red", "green", "blue")):
            fields.append((c, "u1", "uchar"))
            values[c] = rgb[:, i]
        fields.append(("label", "<u4", "uint"))
        values["label"] = lab.astype(np.uint32)
    if center_score is not None:
        score = np.asarray(center_score, dtype=np.float32).reshape(-1)
        if score.size != n:
            raise FormatError(f"center_score has {score.size} entries but xyz has {n} points")
        fields.append(("center_score", "<f4", "float"))
        values["center_score"] = score
    table = np.empty(n, dtype=[(name, dt) for name, dt, _ in fields])
    for name, _, _ in fields:
        table[name] = values[name]
    header = "ply\nformat {} 1.0\ncomment written by fpcc_ros msg_tools\nelement vertex {}\n{}end_header\n".format(
        "binary_little_endian" if binary else "ascii",
        n,
        "".join(f"property {ply} {name}\n" for name, _, ply in fields),
    )

    def write(f: Any) -> None:
        f.write(header.encode("ascii"))
        if binary:
            f.write(table.tobytes())
        else:
            fmt = " ".join("%.9g" if dt.endswith(("f4", "f8")) else "%d" for _, dt, _ in fields)
            np.savetxt(f, table, fmt=fmt)

    _atomic_write(Path(path), write)


# -- PCD ------------------------------------------------------------------------------------------
def read_pcd(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """ASCII or binary PCD (v0.7): x, y, z plus other fields in ``extra`` (fields with COUNT > 1
    as (N, COUNT)); organized clouds (HEIGHT > 1) come back as (H, W, ...). binary_compressed is
    not supported (error says how to convert)."""
    with open(path, "rb") as f:
        header = _read_header(f, path, b"", b"DATA")
        meta: dict[str, list[str]] = {}
        for line in header:
            tok = line.split()
            if tok and not tok[0].startswith("#"):
                meta[tok[0].upper()] = tok[1:]
        data_kind = (meta.get("DATA") or ["?"])[0].lower()
        if data_kind == "binary_compressed":
            raise FormatError(f"PCD {str(path)!r} is binary_compressed, which is not supported; convert it "
                              f"first, e.g. `pcl_convert_pcd_ascii_binary in.pcd out.pcd 1` (binary) or 0 (ascii)")
        if data_kind not in ("ascii", "binary"):
            raise FormatError(f"PCD {str(path)!r}: unknown DATA {data_kind!r} (ascii or binary)")
        try:
            names = meta["FIELDS"]
            sizes = [int(s) for s in meta["SIZE"]]
            kinds = [t.upper() for t in meta["TYPE"]]
            counts = [int(c) for c in meta.get("COUNT", ["1"] * len(names))]
            width = int(meta["WIDTH"][0])
            height = int(meta.get("HEIGHT", ["1"])[0])
            npoints = int(meta.get("POINTS", [str(width * height)])[0])
        except (KeyError, ValueError, IndexError) as err:
            raise FormatError(f"PCD {str(path)!r}: bad or missing header entry ({err}); need FIELDS, SIZE, "
                              f"TYPE, WIDTH") from err
        if not (len(names) == len(sizes) == len(kinds) == len(counts)):
            raise FormatError(f"PCD {str(path)!r}: FIELDS/SIZE/TYPE/COUNT have different lengths "
                              f"({len(names)}/{len(sizes)}/{len(kinds)}/{len(counts)})")
        codes = []
        for name, size, kind in zip(names, sizes, kinds):
            if kind not in ("I", "U", "F") or size not in (1, 2, 4, 8) or (kind == "F" and size not in (4, 8)):
                raise FormatError(f"PCD {str(path)!r}: field {name!r} has unsupported TYPE {kind} SIZE {size}")
            codes.append(f"<{kind.lower()}{size}")  # I -> i, U -> u, F -> f
        for axis in "xyz":
            if axis not in names:
                raise FormatError(f"PCD {str(path)!r} has no field {axis!r} (fields: {names})")
        if data_kind == "binary":
            dt = np.dtype([(n if n != "_" else f"_pad{i}", c, (k,) if k > 1 else ())
                           for i, (n, c, k) in enumerate(zip(names, codes, counts))])
            buf = f.read(dt.itemsize * npoints)
            if len(buf) < dt.itemsize * npoints:
                raise FormatError(f"PCD {str(path)!r} is truncated: {npoints} points need "
                                  f"{dt.itemsize * npoints} bytes, file has {len(buf)}")
            table = np.frombuffer(buf, dtype=dt, count=npoints)
            columns = {n: np.array(table[n]) for n in names if n != "_"}
        else:
            table = np.loadtxt(f, dtype=np.float64, ndmin=2, max_rows=npoints) if npoints else np.zeros((0, sum(counts)))
            if table.shape[0] != npoints or table.shape[1] != sum(counts):
                raise FormatError(f"PCD {str(path)!r}: expected {npoints} rows of {sum(counts)} values, got "
                                  f"{table.shape[0]} rows of {table.shape[1]}")
            columns = {}
            col = 0
            for n, c, k in zip(names, codes, counts):
                if n != "_":
                    block = table[:, col:col + k]
                    columns[n] = (block[:, 0] if k == 1 else block).astype(c.replace("<", "="))
                col += k
    xyz = np.stack([columns.pop(a).astype(np.float32) for a in "xyz"], axis=-1)
    if height > 1 and width * height == npoints:
        xyz = xyz.reshape(height, width, 3)
        columns = {n: v.reshape((height, width) + v.shape[1:]) for n, v in columns.items()}
    return xyz, columns
