"""The repository is a valid ament_python package and pip package."""

from __future__ import annotations

import configparser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_package_xml_validates_with_catkin_pkg() -> None:
    catkin_pkg = pytest.importorskip("catkin_pkg.package", reason="catkin_pkg (the [dev] extra) is not installed")
    package = catkin_pkg.parse_package(str(ROOT / "package.xml"))
    package.validate()
    assert package.name == "selfcontra_ros"
    assert package.package_format == 3
    assert package.get_build_type() == "ament_python"
    exec_depends = {dep.name for dep in package.exec_depends}
    ros_packages = ("rclpy", "sensor_msgs", "stereo_msgs", "geometry_msgs", "nav_msgs", "std_msgs")
    for needed in (*ros_packages, "tf2_ros_py", "tf2_msgs"):  # tf2: pose_source tf
        assert needed in exec_depends


def test_ament_layout() -> None:
    assert (ROOT / "resource" / "selfcontra_ros").is_file(), "ament index marker missing"
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    assert cfg["install"]["install_scripts"] == "$base/lib/selfcontra_ros"
    assert cfg["develop"]["script_dir"] == "$base/lib/selfcontra_ros"
    setup_py = (ROOT / "setup.py").read_text()
    for fragment in ("share/ament_index/resource_index/packages", "config/*", "package.xml"):
        assert fragment in setup_py


def test_config_files_are_found() -> None:
    from selfcontra_ros.resources import config_file

    for name in ("fastdds_profile.xml", "labeler.yaml"):
        assert config_file(name).is_file()
