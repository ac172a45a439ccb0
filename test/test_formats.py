"""Scene files: NPZ / text / PLY / PCD, checked against files written by hand (struct, text)."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from msg_tools import formats
from msg_tools.formats import FormatError, read_scene, write_npz, write_ply

XYZ = np.array([[0.5, -1.25, 2.0], [np.nan, np.nan, np.nan], [3.0, 4.0, 5.5], [-0.125, 0.0, 1.0]], np.float32)
INST = np.array([1, 0, 2, 2], np.int32)
SCORE = np.array([0.25, 0.0, 1.0, 0.5], np.float32)


def test_npz_round_trip_unorganized_and_organized(tmp_path):
    path = tmp_path / "scene.npz"
    write_npz(path, XYZ, INST, SCORE, part_radius=0.035, part_name="bolt", seed=7, camera_K=np.eye(3))
    xyz, extra = read_scene(path)
    assert xyz.dtype == np.float32
    np.testing.assert_array_equal(xyz, XYZ)
    np.testing.assert_array_equal(extra["instance"], INST)
    assert extra["instance"].dtype == np.int32 and extra["center_score"].dtype == np.float32
    np.testing.assert_array_equal(extra["center_score"], SCORE)
    assert extra["part_radius"] == pytest.approx(0.035) and extra["part_name"] == "bolt" and extra["seed"] == 7
    np.testing.assert_array_equal(extra["camera_K"], np.eye(3))
    # organized, written with plain numpy (not our writer)
    org = tmp_path / "org.npz"
    np.savez(org, points=XYZ.reshape(2, 2, 3), instance=INST.reshape(2, 2), center_score=SCORE.reshape(2, 2),
             part_radius=np.float32(0.02))
    xyz, extra = read_scene(org)
    assert xyz.shape == (2, 2, 3) and extra["instance"].shape == (2, 2)
    np.testing.assert_array_equal(xyz.reshape(-1, 3), XYZ)
    assert list(tmp_path.iterdir()) and not [p for p in tmp_path.iterdir() if "partial" in p.name]


def test_npz_errors(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, xyz=XYZ)
    with pytest.raises(FormatError, match="no 'points' array.*xyz"):
        read_scene(bad)
    mismatch = tmp_path / "mismatch.npz"
    np.savez(mismatch, points=XYZ, instance=INST[:3])
    with pytest.raises(FormatError, match="'instance' has shape \\(3,\\)"):
        read_scene(mismatch)


def test_paper_and_peer_text(tmp_path):
    paper = tmp_path / "paper.txt"
    paper.write_text("# x y z score instance\n0.5 -1.25 2 0.25 1\nnan nan nan 0 0\n3 4 5.5 1.0 2\n-0.125 0 1 0.5 2\n")
    xyz, extra = read_scene(paper)
    np.testing.assert_array_equal(xyz, XYZ)
    np.testing.assert_array_equal(extra["instance"], INST)
    np.testing.assert_array_equal(extra["center_score"], SCORE)
    peer = tmp_path / "peer.txt"
    peer.write_text("0.5,-1.25,2,1,0.25\nnan,nan,nan,0,0\n3,4,5.5,2,1.0\n-0.125,0,1,2,0.5\n")
    for cols in ("peer", formats.PEER_COLUMNS):
        xyz, extra = read_scene(peer, columns=cols)
        np.testing.assert_array_equal(xyz, XYZ)
        np.testing.assert_array_equal(extra["instance"], INST)
        np.testing.assert_array_equal(extra["center_score"], SCORE)
    # read with the paper's order the same file swaps the meaning: shows columns= matters
    _, wrong = read_scene(peer)
    assert not np.array_equal(wrong["instance"], INST)
    xyz_only = tmp_path / "xyz.txt"
    xyz_only.write_text("1 2 3\n4 5 6\n")
    xyz, extra = read_scene(xyz_only)
    assert xyz.tolist() == [[1, 2, 3], [4, 5, 6]] and extra == {}
    wide = tmp_path / "wide.txt"
    wide.write_text("1 2 3 4 5 6\n")
    with pytest.raises(FormatError, match="6 columns"):
        read_scene(wide)
    with pytest.raises(FormatError, match="unknown columns preset"):
        read_scene(paper, columns="nope")


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_ply_round_trip(tmp_path, binary):
    path = tmp_path / "out.ply"
    write_ply(path, XYZ.reshape(2, 2, 3), labels=INST, center_score=SCORE, binary=binary)
    head = path.read_bytes()[:200]
    assert (b"binary_little_endian" in head) == binary
    xyz, extra = read_scene(path)
    np.testing.assert_array_equal(xyz, XYZ)
    np.testing.assert_array_equal(extra["label"], INST)
    np.testing.assert_array_equal(extra["center_score"], SCORE)
    assert (extra["red"][0], extra["green"][0], extra["blue"][0]) == (0xF3, 0xC3, 0x00)  # label 1
    assert (extra["red"][1], extra["green"][1], extra["blue"][1]) == (128, 128, 128)  # label 0


def test_ply_binary_written_by_hand(tmp_path):
    header = (b"ply\nformat binary_little_endian 1.0\ncomment by hand\nelement vertex 2\n"
              b"property float x\nproperty float y\nproperty float z\nproperty uchar red\n"
              b"property ushort ring\nproperty double t\nelement face 1\n"
              b"property list uchar int vertex_indices\nend_header\n")
    body = struct.pack("<fffBHd", 1.0, 2.0, 3.0, 200, 60000, 0.5) + struct.pack("<fffBHd", -1.0, np.nan, 9.0, 7, 3, -2.0)
    body += struct.pack("<Biii", 3, 0, 1, 1)
    path = tmp_path / "hand.ply"
    path.write_bytes(header + body)
    xyz, extra = read_scene(path)
    np.testing.assert_array_equal(xyz, np.float32([[1, 2, 3], [-1, np.nan, 9]]))
    assert extra["red"].tolist() == [200, 7] and extra["ring"].tolist() == [60000, 3]
    assert extra["t"].tolist() == [0.5, -2.0]
    # big endian variant
    be = tmp_path / "be.ply"
    be.write_bytes(header.replace(b"binary_little_endian", b"binary_big_endian")
                   + struct.pack(">fffBHd", 1.0, 2.0, 3.0, 200, 60000, 0.5) + struct.pack(">fffBHd", -1, 0, 9, 7, 3, -2))
    xyz, extra = read_scene(be)
    assert xyz.tolist() == [[1, 2, 3], [-1, 0, 9]] and extra["ring"].tolist() == [60000, 3]
    # truncated
    cut = tmp_path / "cut.ply"
    cut.write_bytes(header + body[:20])
    with pytest.raises(FormatError, match="truncated"):
        read_scene(cut)


def test_ply_ascii_written_by_hand(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nproperty int label\nelement face 1\nproperty list uchar int vertex_indices\n"
                    "end_header\n0 0 1 4\n1 0 1 5\n0 1 1 4\n3 0 1 2\n")
    xyz, extra = read_scene(path)
    assert xyz.tolist() == [[0, 0, 1], [1, 0, 1], [0, 1, 1]] and extra["label"].tolist() == [4, 5, 4]
    nox = tmp_path / "nox.ply"
    nox.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nproperty float y\n"
                   "property float z\nend_header\n0 0 0\n")
    with pytest.raises(FormatError, match="no 'x' property"):
        read_scene(nox)


PCD_HEADER = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb label normal _\n"
              "SIZE 4 4 4 4 4 4 1\nTYPE F F F F U F U\nCOUNT 1 1 1 1 1 3 2\nWIDTH {w}\nHEIGHT {h}\n"
              "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {kind}\n")


def pcd_rows():
    return [(0.5, -1.25, 2.0, 1.5, 7, (0.0, 0.0, 1.0)), (np.nan, np.nan, np.nan, 0.0, 0, (1.0, 0.0, 0.0)),
            (3.0, 4.0, 5.5, 2.5, 3, (0.0, 1.0, 0.0)), (-0.125, 0.0, 1.0, 3.5, 9, (0.5, 0.5, 0.0))]


@pytest.mark.parametrize("kind", ["ascii", "binary"])
@pytest.mark.parametrize("organized", [False, True], ids=["unorganized", "organized"])
def test_pcd(tmp_path, kind, organized):
    rows = pcd_rows()
    w, h = (2, 2) if organized else (4, 1)
    header = PCD_HEADER.format(w=w, h=h, n=4, kind=kind).encode()
    if kind == "binary":
        body = b"".join(struct.pack("<ffffIfffBB", x, y, z, c, lab, *nrm, 0xAA, 0xBB) for x, y, z, c, lab, nrm in rows)
    else:
        body = "".join(f"{x} {y} {z} {c} {lab} {nrm[0]} {nrm[1]} {nrm[2]} 0 0\n"
                       for x, y, z, c, lab, nrm in rows).encode()
    path = tmp_path / "c.pcd"
    path.write_bytes(header + body)
    xyz, extra = read_scene(path)
    expect = np.float32([r[:3] for r in rows])
    assert xyz.shape == ((2, 2, 3) if organized else (4, 3))
    np.testing.assert_array_equal(xyz.reshape(-1, 3), expect)
    assert extra["label"].reshape(-1).tolist() == [7, 0, 3, 9]
    np.testing.assert_array_equal(extra["rgb"].reshape(-1), np.float32([1.5, 0, 2.5, 3.5]))
    assert extra["normal"].shape == ((2, 2, 3) if organized else (4, 3))
    np.testing.assert_array_equal(extra["normal"].reshape(-1, 3), np.float32([r[5] for r in rows]))
    assert "_" not in extra


def test_pcd_errors(tmp_path):
    comp = tmp_path / "comp.pcd"
    comp.write_bytes(PCD_HEADER.format(w=4, h=1, n=4, kind="binary_compressed").encode() + b"\x00" * 40)
    with pytest.raises(FormatError, match="binary_compressed.*not supported.*pcl_convert_pcd_ascii_binary"):
        read_scene(comp)
    short = tmp_path / "short.pcd"
    short.write_bytes(PCD_HEADER.format(w=4, h=1, n=4, kind="binary").encode() + b"\x00" * 40)
    with pytest.raises(FormatError, match="truncated"):
        read_scene(short)
    noz = tmp_path / "noz.pcd"
    noz.write_text("VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n")
    with pytest.raises(FormatError, match="no field 'z'"):
        read_scene(noz)


def test_unknown_extension_and_missing_file(tmp_path):
    odd = tmp_path / "scene.xyz"
    odd.write_text("1 2 3\n")
    with pytest.raises(FormatError, match=r"unsupported scene file extension '.xyz'.*\.npz, \.txt, \.ply, \.pcd"):
        read_scene(odd)
    with pytest.raises(FormatError, match="does not exist"):
        read_scene(tmp_path / "missing.ply")
    with pytest.raises(FormatError, match="columns= applies to .txt"):
        read_scene(tmp_path / "x.ply", columns="peer")
