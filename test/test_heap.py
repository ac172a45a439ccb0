"""fpcc_ros.heap: freed frame-sized memory stays in the process for the next frame."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

# A frame's worth of arrays (~40 MB in sizes from 0.5 to 12 MB, touched) allocated and freed on
# a worker thread, as the node does, five times; the minor page faults of the last round (glibc's
# adaptive thresholds have settled by then) are printed.
_FRAMES = """
import json, resource, sys, threading
import numpy as np
from fpcc_ros.heap import retain_freed_memory
applied = retain_freed_memory() if sys.argv[1] == "retain" else False
SIZES_MB = (12, 9, 7, 5, 3.7, 2, 1, 0.5) * 2
faults = []
def frames():
    for _ in range(5):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        arrays = [np.ones(int(mb * (1 << 20)), np.uint8) for mb in SIZES_MB]
        del arrays
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
worker = threading.Thread(target=frames)
worker.start()
worker.join()
print(json.dumps({"applied": applied, "faults": faults[-1]}))
"""
FRAME_PAGES = int(2 * 40.2 * (1 << 20)) // 4096


def _last_frame_faults(mode: str) -> dict:
    result = subprocess.run([sys.executable, "-c", _FRAMES, mode], capture_output=True,
                            text=True, timeout=60, check=True)
    return json.loads(result.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mallopt is glibc's")
def test_a_worker_thread_reuses_freed_frame_memory_instead_of_faulting_it_in_again():
    default = _last_frame_faults("default")
    retained = _last_frame_faults("retain")
    # glibc's defaults give part of the worker's memory back: every round faults it in again
    # (2.9k of 20.6k pages here; the bench's 20-part bin: 5-8k faults per frame)
    assert default["faults"] > FRAME_PAGES // 20, default
    assert retained["applied"] is True
    assert retained["faults"] < default["faults"] // 10, (retained, default)


def test_the_bench_reports_whether_the_settings_apply(monkeypatch):
    from fpcc_ros import heap
    from fpcc_ros.bench import heap_setting

    monkeypatch.setattr(heap, "retained", False)
    assert "returns freed memory" in heap_setting()
    monkeypatch.setattr(heap, "retained", True)
    assert "retains freed memory" in heap_setting()


@pytest.mark.parametrize("argv, retains", [
    (["bench", "--no-such-option"], True),
    (["segment", "--no-such-option"], True),
    (["part-info", "--no-such-option"], False),   # like train and synth: glibc's defaults
])
def test_fpcc_keeps_freed_memory_only_for_the_commands_that_segment_frames(monkeypatch, argv,
                                                                          retains):
    from fpcc_ros import cli

    calls = []
    monkeypatch.setattr(cli, "retain_freed_memory", lambda: calls.append(True))
    monkeypatch.setattr(sys, "argv", ["fpcc"])
    with pytest.raises(SystemExit):   # argparse rejects the option after the decision
        cli.main(argv)
    assert bool(calls) is retains
