"""`make` installs the package itself into the venv (README: the tools are on the venv's PATH)."""
import subprocess
import sys
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent


@pytest.mark.skipif(sys.prefix == sys.base_prefix, reason="not running in a virtual environment")
@pytest.mark.parametrize("tool, expect", [("fpcc", "COMMAND"), ("segmenter", None)])
def test_console_scripts_in_the_venv(tool, expect):
    exe = BIN / tool
    assert exe.is_file(), f"{exe} missing: `make venv` installs the package editable into the venv"
    if expect:
        out = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0 and expect in out.stdout
