"""`fpcc segment` and `fpcc demo` stopped by SIGINT or SIGTERM while working (issue 26): the
output bag is complete or absent -- its temporary folder removed -- never half-written under
its final name; the exit code is 128 + the signal; `demo` stops its node first."""
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import REPO, TEST_DATA
from fpcc_ros.replay import isolated_ros_env

TINY = TEST_DATA / "tiny_fpcc.onnx"
SIGNALS = pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM],
                                  ids=["SIGINT", "SIGTERM"])


def _fpcc(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "fpcc_ros.cli", *args], cwd=REPO,
                            env=isolated_ros_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _wait_for(predicate, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert proc.poll() is None, f"exited {proc.returncode} first:\n{proc.stdout.read()}"
        assert time.monotonic() < deadline, "timed out waiting"
        time.sleep(0.005)


def _partials(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if ".partial-" in p.name]


@SIGNALS
def test_segment_interrupted_while_writing_its_bag_leaves_no_bag(tmp_path, sig):
    out = tmp_path / "segmented"
    proc = _fpcc("segment", str(REPO / "bags" / "demo"), "--out", str(out), "--model", str(TINY))
    _wait_for(lambda: bool(_partials(tmp_path)), proc)   # the bag is being written
    proc.send_signal(sig)
    text = proc.communicate(timeout=60)[0]
    assert proc.returncode == 128 + sig, text
    assert "interrupted" in text and "Traceback" not in text, text
    assert not out.exists(), text
    assert _partials(tmp_path) == [], text


@pytest.mark.ros
@SIGNALS
def test_demo_interrupted_stops_its_node_and_leaves_no_bag(tmp_path, sig):
    out = tmp_path / "demo"
    proc = _fpcc("demo", "--out", str(out), "--model", str(TINY))
    log = out / "node.log"
    _wait_for(lambda: log.is_file() and "listening on" in log.read_text(), proc)
    proc.send_signal(sig)
    text = proc.communicate(timeout=90)[0]
    assert proc.returncode == 128 + sig, text
    assert "interrupted" in text and "Traceback" not in text, text
    assert not (out / "segmented_bag").exists()
    assert _partials(out) == []
    node_log = log.read_text()
    assert "totals:" in node_log and "Traceback" not in node_log, node_log   # stopped in order
