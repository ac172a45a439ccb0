"""scripts/time_train_batches.py: each batch size trains on the same blocks and is reported
against the first, with the CPU named; a block count that some size cannot split is refused."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from test_dataset import write_fake_scenes

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "time_train_batches.py"


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
def test_every_batch_size_is_timed_against_the_first(tmp_path):
    write_fake_scenes(tmp_path / "scenes", count=3)
    result = _run("--data", str(tmp_path / "scenes"), "--batches", "2", "1", "--blocks", "2",
                  "--rounds", "1", "--threads", "1")
    assert result.returncode == 0, result.stderr[-2000:]
    assert re.search(r"^CPU: .+, 1 torch threads, (bf16|fp32)$", result.stdout, re.M), result.stdout
    rows = re.findall(r"^  batch (\d+)\s+\d+ ms/step\s+(\d+) points/s\s+([\d.]+)x$",
                      result.stdout, re.M)
    assert [size for size, _, _ in rows] == ["2", "1"], result.stdout
    assert rows[0][2] == "1.00"
    assert all(int(rate) > 0 and float(ratio) > 0 for _, rate, ratio in rows)


def test_blocks_that_a_batch_size_cannot_split_are_refused(tmp_path):
    result = _run("--data", str(tmp_path), "--batches", "2", "4", "--blocks", "6")
    assert result.returncode == 2
    assert "--blocks 6 must be a multiple of every --batches size [2, 4]" in result.stderr


def test_too_few_blocks_name_the_folder_count(tmp_path):
    write_fake_scenes(tmp_path / "scenes", count=1, organised_first=False)
    result = _run("--data", str(tmp_path / "scenes"), "--batches", "1", "--blocks", "64")
    assert result.returncode == 2
    assert re.search(r"--data holds \d+ blocks, fewer than --blocks 64", result.stderr)
