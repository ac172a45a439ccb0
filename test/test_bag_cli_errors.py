"""`fpcc segment` on bad bags and files: clear errors, atomic outputs, one output per input.

Bags are built here with msg_tools.bag.BagWriter from cloud_factory clouds (rosbags flavour);
outputs are read back and checked against the contract with cloud_factory.check_output.
"""
from pathlib import Path

import numpy as np
import pytest

import cloud_factory as cf
from conftest import TEST_DATA
from fpcc_ros.cli import main as fpcc
from msg_tools.bag import BagWriter, list_topics, read_messages
from msg_tools.instances import create_pose_array
from msg_tools.msg_types import ROSBAGS

MODEL = str(TEST_DATA / "tiny_fpcc.onnx")
CLOUD = "sensor_msgs/msg/PointCloud2"
OUT_TOPICS = ("/segmented_points", "/instances", "/instance_markers")


def _cloud(i, layout=None):
    xyz = cf.scene_xyz(24, 30, seed=i, spheres=4)
    return cf.make_cloud(xyz, layout or cf.LAYOUTS[i % len(cf.LAYOUTS)],
                         stamp=(1_700_000_000 + i) * 1_000_000_000 + 123, types=ROSBAGS)


def _bag(path: Path, clouds, compress=True, topic="/cam/points", extra=()):
    with BagWriter(path, compress=compress) as w:
        if clouds:
            w.add_topic(topic, CLOUD)
        for i, msg in enumerate(clouds):
            w.write(topic, 5_000_000 + i * 1000, msg)   # receive times differ from stamps
        for t, ts, msg in extra:
            w.write(t, ts, msg)
    return path


def _segment(capsys, *args):
    rc = fpcc(["segment", *map(str, args), "--model", MODEL])
    out, err = capsys.readouterr()
    return rc, out, err


def _leftovers(parent: Path):
    return [p.name for p in parent.iterdir() if ".partial-" in p.name]


@pytest.fixture
def good_bag(tmp_path):
    return _bag(tmp_path / "scene", [_cloud(i) for i in range(4)])


# ----------------------------------------------------------------------------- unreadable bags

@pytest.mark.parametrize("cut", ["half", "last_20_bytes", "empty"])
def test_truncated_mcap_is_a_clear_error_and_writes_nothing(tmp_path, capsys, cut):
    bag = _bag(tmp_path / "rec", [_cloud(i) for i in range(3)], compress=False)
    mcap = bag / "rec.mcap"
    raw = mcap.read_bytes()
    mcap.write_bytes({"half": raw[:len(raw) // 2], "last_20_bytes": raw[:-20], "empty": b""}[cut])
    rc, _, err = _segment(capsys, bag, "--out", tmp_path / "out")
    assert rc == 2
    assert f"cannot open bag '{bag}'" in err and "truncated or corrupt" in err
    assert "mcap recover" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists() and _leftovers(tmp_path) == []


def test_corrupt_compressed_chunk_is_a_clear_error_and_writes_nothing(tmp_path, capsys):
    bag = _bag(tmp_path / "rec", [_cloud(i) for i in range(3)])
    mcap = bag / "rec.mcap"
    raw = bytearray(mcap.read_bytes())
    mid = len(raw) // 3
    raw[mid:mid + 512] = bytes(range(256)) * 2
    mcap.write_bytes(bytes(raw))
    rc, _, err = _segment(capsys, bag, "--out", tmp_path / "out")
    assert rc == 2
    assert f"bag '{bag}' is damaged" in err and "corrupt" in err
    assert not (tmp_path / "out").exists() and _leftovers(tmp_path) == []


def test_unknown_topic_names_the_topics_the_bag_has(good_bag, capsys, tmp_path):
    rc, _, err = _segment(capsys, good_bag, "--topic", "/nope", "--out", tmp_path / "out")
    assert rc == 2
    assert "has no topic '/nope'; it has: /cam/points (sensor_msgs/msg/PointCloud2)" in err
    assert not (tmp_path / "out").exists()


def test_a_topic_of_another_type_is_refused(tmp_path, capsys):
    poses = create_pose_array(ROSBAGS.header("cam", 1, 0), np.zeros((1, 3)), ROSBAGS)
    bag = _bag(tmp_path / "mixed", [_cloud(0)], extra=[("/poses", 9, poses)])
    rc, _, err = _segment(capsys, bag, "--topic", "/poses", "--out", tmp_path / "out")
    assert rc == 2 and "'/poses'" in err
    assert "is geometry_msgs/msg/PoseArray, not sensor_msgs/msg/PointCloud2" in err


def test_a_bag_without_pointcloud2_is_a_clear_error(tmp_path, capsys):
    poses = create_pose_array(ROSBAGS.header("cam", 1, 0), np.zeros((2, 3)), ROSBAGS)
    bag = _bag(tmp_path / "poses_only", [], extra=[("/poses", 9, poses)])
    rc, _, err = _segment(capsys, bag, "--out", tmp_path / "out")
    assert rc == 2
    assert ("has no sensor_msgs/msg/PointCloud2 topic; it has: /poses "
            "(geometry_msgs/msg/PoseArray)") in err
    assert not (tmp_path / "out").exists()


def test_a_directory_that_is_not_a_bag_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "notabag").mkdir()
    (tmp_path / "notabag" / "x.mcap").write_bytes(b"junk")
    rc, _, err = _segment(capsys, tmp_path / "notabag", "--out", tmp_path / "out")
    assert rc == 2 and "has no metadata.yaml" in err and "pass that .mcap file" in err


# ----------------------------------------------------------------------------- outputs

def test_an_existing_output_is_kept_without_force_and_replaced_with_it(good_bag, tmp_path, capsys):
    out = _bag(tmp_path / "out", [_cloud(9)])          # an older result under the same name
    before = sorted((p.name, p.read_bytes()) for p in out.iterdir())
    rc, _, err = _segment(capsys, good_bag, "--out", out)
    assert rc == 2 and "already exists" in err and "--force" in err
    assert sorted((p.name, p.read_bytes()) for p in out.iterdir()) == before

    rc, _, err = _segment(capsys, good_bag, "--out", out, "--force")
    assert rc == 0, err
    assert set(list_topics(out)) == {"/cam/points", *OUT_TOPICS}
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("fault", [KeyboardInterrupt])
def test_the_output_appears_only_when_complete(good_bag, tmp_path, capsys, monkeypatch, fault):
    """Interrupted (Ctrl-C) or failed half-way: no output under the asked name, no leftovers;
    while writing, the bag lives under a hidden temporary name beside it."""
    import fpcc_ros.frame as frame
    real, seen = frame.process_cloud, []
    out = tmp_path / "out"

    def process_then_fail(msg, pipeline, types):
        seen.append((out.exists(), _leftovers(tmp_path)))
        if len(seen) == 3:
            raise fault("injected at message 3")
        return real(msg, pipeline, types)

    monkeypatch.setattr(frame, "process_cloud", process_then_fail)
    if fault is KeyboardInterrupt:
        rc = fpcc(["segment", str(good_bag), "--out", str(out), "--model", MODEL])
        assert rc == 130
    else:
        with pytest.raises(RuntimeError):
            fpcc(["segment", str(good_bag), "--out", str(out), "--model", MODEL])
    assert len(seen) == 3
    assert all(not exists and len(partial) == 1 and partial[0].startswith(".out.partial-")
               for exists, partial in seen)
    assert not out.exists() and _leftovers(tmp_path) == []


def test_every_input_message_yields_one_output_per_topic_with_its_stamp(tmp_path, capsys):
    clouds = [_cloud(i) for i in range(len(cf.LAYOUTS))]      # every legal layout once
    bag = _bag(tmp_path / "scene", clouds)
    rc, stdout, err = _segment(capsys, bag, "--out", tmp_path / "out")
    assert rc == 0, err
    n = len(clouds)
    assert (f"{n} input messages on /cam/points: {n} segmented (one output per topic each, "
            f"same stamps), 0 malformed or failed and skipped") in stdout
    got = {}
    for topic, _, ts, msg in read_messages(tmp_path / "out"):
        got.setdefault(topic, []).append((ts, msg))
    receive_times = [5_000_000 + i * 1000 for i in range(n)]
    assert [ts for ts, _ in got["/cam/points"]] == receive_times
    for topic in OUT_TOPICS:
        assert [ts for ts, _ in got[topic]] == receive_times, topic
    for i, cloud in enumerate(clouds):
        outputs = {t.lstrip("/"): got[t][i][1] for t in OUT_TOPICS}
        cf.check_output(cloud, outputs, cf.Kind("bag", True, None), roi=None)


def test_a_malformed_message_in_a_bag_is_counted_and_reported(tmp_path, capsys):
    clouds = [_cloud(i, "xyz32") for i in range(4)]
    bad = clouds[2]
    bad.data = bad.data[:-7]                                   # truncated
    bag = _bag(tmp_path / "scene", clouds)
    rc, stdout, err = _segment(capsys, bag, "--out", tmp_path / "out")
    assert rc == 1
    assert "message at 5002000 ns skipped: PointCloud2 data has" in err and "truncated" in err
    assert ("4 input messages on /cam/points: 3 segmented (one output per topic each, same "
            "stamps), 1 malformed or failed and skipped") in stdout
    for topic in OUT_TOPICS:
        stamps = [cf.stamp_of(m if topic != "/instance_markers" else m.markers[0])
                  for _, _, _, m in read_messages(tmp_path / "out", [topic])]
        assert stamps == [cf.stamp_of(c) for k, c in enumerate(clouds) if k != 2]


# ----------------------------------------------------------------------------- checkpoints

class _Payload:
    """Unpickling this runs code (creates a file): what weights_only=True must refuse."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_torch_checkpoints_load_with_weights_only(tmp_path):
    torch = pytest.importorskip("torch")
    from fpcc_ros.training.train import load_checkpoint

    good = tmp_path / "good.pt"
    torch.save({"model": {"w": torch.ones(2)}, "epoch": 3}, good)
    state = load_checkpoint(good)
    assert state["epoch"] == 3 and torch.equal(state["model"]["w"], torch.ones(2))

    marker = tmp_path / "code_ran"
    evil = tmp_path / "evil.pt"
    torch.save({"model": {}, "extra": _Payload(marker)}, evil)
    with pytest.raises(Exception, match="[Ww]eights only load failed"):
        load_checkpoint(evil)
    assert not marker.exists()


def test_a_frame_that_fails_is_skipped_and_the_rest_still_come_out(good_bag, tmp_path, capsys,
                                                                    monkeypatch):
    """As in the node: an exception in one frame costs that frame, not the bag (exit code 1)."""
    import fpcc_ros.frame as frame
    real, calls = frame.process_cloud, []

    def fail_third(msg, pipeline, types):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("injected at message 3")
        return real(msg, pipeline, types)

    monkeypatch.setattr(frame, "process_cloud", fail_third)
    out = tmp_path / "out"
    rc = fpcc(["segment", str(good_bag), "--out", str(out), "--model", MODEL])
    err = capsys.readouterr().err
    assert rc == 1 and "injected at message 3" in err
    counts = {}
    for topic, _, _, _ in read_messages(out):
        counts[topic] = counts.get(topic, 0) + 1
    inputs = counts.pop("/cam/points")
    assert inputs == len(calls) and all(n == inputs - 1 for n in counts.values())
