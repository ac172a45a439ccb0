"""scripts/time_net_widths.py: every width exports, runs and is reported against the shipped one."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "time_net_widths.py"


@pytest.mark.slow
def test_every_width_is_timed_against_the_shipped_one():
    result = subprocess.run([sys.executable, str(SCRIPT), "--points", "300", "--runs", "2"],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    rows = dict(re.findall(r"^  (.+?)\s+[\d.]+ ms\s+([\d.]+)x$", result.stdout, re.M))
    assert set(rows) == {"shipped", "global 512", "edge 48", "edge 32", "edge 32, global 512",
                         "all but edge halved"}, result.stdout
    assert float(rows["shipped"]) == 1.0
    assert all(float(ratio) > 0 for ratio in rows.values())
