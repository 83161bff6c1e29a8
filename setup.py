"""Build script for selfcontra_ros (ament_python layout, also pip-installable).

colcon (with colcon-ros) reads this file like any ROS 2 Python package and
installs the node executables to ``lib/selfcontra_ros/``; plain ``pip
install .`` installs the same entry points to the environment's ``bin/``.
"""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "selfcontra_ros"
# The ROS 2 packages the nodes import, as PyPI wheels name them after the
# distribution prefix ("ros-" for Kilted, "ros-jazzy-" for Jazzy).
ROS_PACKAGES = [
    "rclpy",
    "rmw-fastrtps-cpp",
    "std-msgs",
    "sensor-msgs",
    "geometry-msgs",
    "stereo-msgs",
    "nav-msgs",
    "ament-index-python",
]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    # The band cue the training's band prior reads (a plain-array model file, never pickle).
    package_data={f"{PACKAGE}.confidence": ["models/*.npz"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(glob("config/*"))),
        (f"share/{PACKAGE}/launch", sorted(glob("launch/*.py"))),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "numba>=0.59",
        "threadpoolctl>=3.1",
        # OpenCV with its contrib modules (ximgproc: the WLS confidence baseline). It replaces
        # opencv-python-headless: both write the same cv2 package, and together they break it.
        "opencv-contrib-python-headless>=4.8",
        "scikit-learn>=1.3",
        "rosbags>=0.10",
        "mcap>=1.1",
        "zstandard>=0.22",  # the bag reader decompresses MCAP chunks itself
        "lz4>=4.0",
        "mcap-ros2-support>=0.5",
        "PyYAML>=6.0",
        "tqdm>=4.60",
        "matplotlib>=3.7",
    ],
    extras_require={
        # One ROS 2 distribution per environment: Kilted's and Jazzy's wheels share
        # distribution names (ros-rclpy 9.x vs 7.x) and cannot be mixed.
        "ros": [f"ros-{name}" for name in ROS_PACKAGES],  # Kilted
        "ros-jazzy": [f"ros-jazzy-{name}" for name in ROS_PACKAGES],
        # `selfcontra batch` on a Ray cluster (local by default); without it the batch runs sequentially.
        "cluster": ["ray>=2.40"],
        "dev": [
            "pytest",
            "pytest-timeout",
            "ruff",
            "mypy",
            "types-PyYAML",
            "catkin-pkg",
            "colcon-common-extensions",
            "colcon-ros",
        ],
    },
    zip_safe=False,  # the band cue model is read from its file next to the module
    maintainer="selfcontra_ros developers",
    maintainer_email="selfcontra-ros@example.invalid",
    description="Self-supervised stereo confidence labels from self-contradiction (Mostegel et al., CVPR 2016).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "selfcontra = selfcontra_ros.cli:main",
            "player = selfcontra_ros.ros.player_node:main",
            "labeler = selfcontra_ros.ros.labeler_node:main",
        ],
    },
)
