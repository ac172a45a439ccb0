"""ament_python package: `colcon build` installs the `segmenter`, `segmenter_managed` and `fpcc`
executables into lib/fpcc_ros (where `ros2 run fpcc_ros segmenter` looks), the ament index
marker, package.xml, the shipped models, config files and the demo bag into share/fpcc_ros."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "fpcc_ros"


def share(folder: str, pattern: str = "*") -> tuple[str, list[str]]:
    return (f"share/{PACKAGE}/{folder}", sorted(p for p in glob(f"{folder}/{pattern}")))


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        share("models", "*.onnx"),
        share("models", "*.json"),
        share("models", "*.pt"),   # torch weights of the shipped model, for `fpcc train --init default`
        share("config"),
        *[(f"share/{PACKAGE}/{d}", glob(f"{d}/*")) for d in sorted(glob("bags/*")) if glob(f"{d}/*")],
    ],
    python_requires=">=3.10",
    install_requires=["setuptools", "numpy", "scipy", "onnxruntime", "threadpoolctl"],
    extras_require={
        # pip-only machines get ROS 2 from PyPI wheels; a ROS install already provides these.
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces"],
        "tools": ["rosbags", "mcap", "mcap-ros2-support", "tqdm", "matplotlib"],
        "train": ["torch==2.13.0", "pybullet", "trimesh", "onnx", "onnxscript"],
        "test": ["pytest", "pytest-timeout", "colcon-common-extensions"],
    },
    zip_safe=True,
    maintainer="fpcc_ros developers",
    maintainer_email="fpcc-ros@example.com",
    description="FPCC-Net instance segmentation for bin picking as a ROS 2 node",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "segmenter = fpcc_ros.segmenter:main",
            "segmenter_managed = fpcc_ros.managed_segmenter:main",   # the lifecycle variant
            "fpcc = fpcc_ros.cli:main",
        ],
    },
)
