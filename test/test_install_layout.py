"""`colcon build` of the package yields the layout `ros2 run fpcc_ros segmenter` relies on:
install/fpcc_ros/lib/fpcc_ros/<exe>, the ament index marker, share/fpcc_ros/package.xml, plus
the shipped model and config. The installed executable must run (here: refuse a bad model)."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

PACKAGE_FILES = ["package.xml", "setup.py", "setup.cfg", "resource", "fpcc_ros", "msg_tools",
                 "models", "config", "bags", "LICENSE", "README.md"]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.exists():
        pytest.fail("colcon is not installed in the test environment (requirements/test.txt)")
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "fpcc_ros"
    src.mkdir(parents=True)
    for name in PACKAGE_FILES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        elif path.exists():
            shutil.copy2(path, src / name)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    result = subprocess.run([str(colcon), "build", "--base-paths", "src"], cwd=ws, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    return ws / "install" / "fpcc_ros"


def test_executables_where_ros2_run_looks(installed):
    for exe in ("segmenter", "segmenter_managed", "fpcc"):
        path = installed / "lib" / "fpcc_ros" / exe
        assert path.is_file() and os.access(path, os.X_OK), f"missing {path}"


def test_ament_index_marker_and_share(installed):
    assert (installed / "share" / "ament_index" / "resource_index" / "packages" / "fpcc_ros").is_file()
    assert (installed / "share" / "fpcc_ros" / "package.xml").is_file()
    assert (installed / "share" / "fpcc_ros" / "models" / "fpcc_default.onnx").is_file()
    assert (installed / "share" / "fpcc_ros" / "models" / "fpcc_default.json").is_file()
    assert (installed / "share" / "fpcc_ros" / "models" / "fpcc_default.pt").is_file()  # --init default
    assert (installed / "share" / "fpcc_ros" / "config" / "fastdds_large_clouds.xml").is_file()


def test_installed_segmenter_runs_and_fails_loudly_on_a_bad_model(installed, tmp_path):
    site = next((installed / "lib").glob("python3*/site-packages"))
    env = {**os.environ, "PYTHONPATH": str(site),
           "AMENT_PREFIX_PATH": f"{installed}:{os.environ.get('AMENT_PREFIX_PATH', '')}"}
    exe = installed / "lib" / "fpcc_ros" / "segmenter"
    missing = tmp_path / "nope.onnx"
    result = subprocess.run([str(exe), "--ros-args", "-p", f"model:={missing}"], env=env,
                            capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert result.returncode == 1
    assert "nope.onnx not found" in result.stderr


def test_installed_package_finds_the_shipped_model_via_the_ament_index(installed, tmp_path):
    site = next((installed / "lib").glob("python3*/site-packages"))
    env = {**os.environ, "PYTHONPATH": str(site), "AMENT_PREFIX_PATH": str(installed)}
    code = ("from fpcc_ros.onnx_model import default_model_path; p = default_model_path(); "
            "print(p); assert p.is_file(), p")
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                            timeout=60, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert str(installed) in result.stdout


def test_installed_managed_segmenter_imports_and_checks_its_parameters(installed, tmp_path):
    """The lifecycle variant loads no model at start-up, so a bad parameter is what it refuses."""
    site = next((installed / "lib").glob("python3*/site-packages"))
    env = {**os.environ, "PYTHONPATH": str(site),
           "AMENT_PREFIX_PATH": f"{installed}:{os.environ.get('AMENT_PREFIX_PATH', '')}"}
    exe = installed / "lib" / "fpcc_ros" / "segmenter_managed"
    result = subprocess.run([str(exe), "--ros-args", "-p", "stale_warn_fraction:=2.0"], env=env,
                            capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "cannot start" in result.stderr and "stale_warn_fraction" in result.stderr
