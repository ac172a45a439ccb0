"""`fpcc demo` (what `make demo` runs) as a new user runs it: no ROS_DOMAIN_ID set beforehand.
It must start the node, replay the demo bag over DDS, and write the bag, summary and PNGs."""
import os
import subprocess
import sys

import pytest

from conftest import REPO, TEST_DATA

pytestmark = pytest.mark.ros


def test_demo_runs_end_to_end_from_a_clean_environment(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("ROS_DOMAIN_ID",
                                                             "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"   # isolation from other test sessions
    out = tmp_path / "demo"
    result = subprocess.run([sys.executable, "-m", "fpcc_ros.cli", "demo", "--out", str(out),
                             "--model", str(TEST_DATA / "tiny_fpcc.onnx")],
                            cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "median latency" in result.stdout and "node stopped cleanly" in result.stdout
    pngs = sorted(out.glob("frame_*.png"))
    assert len(pngs) == 3 and all(p.read_bytes()[:4] == b"\x89PNG" for p in pngs)
    assert (out / "segmented_bag" / "metadata.yaml").is_file()
