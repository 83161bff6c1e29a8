"""The colcon route: a workspace build installs the executables where ``ros2 run`` looks."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXECUTABLES = ("labeler", "player", "selfcontra")


def _colcon() -> str:
    colcon = shutil.which("colcon") or str(Path(sys.executable).parent / "colcon")
    if not Path(colcon).is_file():
        pytest.skip("colcon is not installed (colcon-common-extensions and colcon-ros, the [dev] extra)")
    return colcon


def _copy_sources(dest: Path) -> None:
    """Copy the files git tracks (or the tree minus build products) into ``dest``."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, check=True, capture_output=True, text=True
        ).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        listed = []
    if not listed:
        shutil.copytree(ROOT, dest, ignore=shutil.ignore_patterns(".venv", ".git", "build", "install", "log"))
        return
    for name in listed:
        source = ROOT / name
        if source.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    colcon = _colcon()
    ws = tmp_path_factory.mktemp("colcon_ws")
    _copy_sources(ws / "src" / "selfcontra_ros")
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    result = subprocess.run(
        [colcon, "build", "--event-handlers", "console_direct-"],
        cwd=ws,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout}\n{result.stderr}"
    return ws


def test_colcon_recognises_an_ament_python_package(workspace: Path) -> None:
    listed = subprocess.run(
        [_colcon(), "list"], cwd=workspace, capture_output=True, text=True, check=True, timeout=60
    ).stdout
    assert "selfcontra_ros" in listed
    assert "(ros.ament_python)" in listed, f"colcon-ros did not classify the package: {listed}"


def test_executables_and_ament_index(workspace: Path) -> None:
    prefix = workspace / "install" / "selfcontra_ros"
    for name in EXECUTABLES:
        executable = prefix / "lib" / "selfcontra_ros" / name
        assert executable.is_file(), f"{executable} missing"
        assert os.access(executable, os.X_OK)
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "selfcontra_ros").is_file()
    assert (prefix / "share" / "selfcontra_ros" / "package.xml").is_file()
    for name in ("labeler.yaml", "fastdds_profile.xml"):
        assert (prefix / "share" / "selfcontra_ros" / "config" / name).is_file()


def test_installed_command_runs_and_finds_installed_config(workspace: Path) -> None:
    prefix = workspace / "install" / "selfcontra_ros"
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = str(prefix)
    help_text = subprocess.run(
        [str(prefix / "lib" / "selfcontra_ros" / "selfcontra"), "--help"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert help_text.returncode == 0, help_text.stderr
    assert "synth" in help_text.stdout and "label" in help_text.stdout
    site = next((prefix / "lib").glob("python3*/site-packages"))
    env["PYTHONPATH"] = str(site)
    found = subprocess.run(
        [sys.executable, "-c", "from selfcontra_ros.resources import config_file; print(config_file('labeler.yaml'))"],
        cwd=workspace,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout.strip()
    assert Path(found) == prefix / "share" / "selfcontra_ros" / "config" / "labeler.yaml"
    # The band cue model travels with the Python package and loads from the install, not the sources.
    cue = subprocess.run(
        [
            sys.executable,
            "-c",
            "from selfcontra_ros.confidence.band_cue import MODEL_FILE, default_band_cue; "
            "print(MODEL_FILE, default_band_cue().n_trees)",
        ],
        cwd=workspace,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout.split()
    assert Path(cue[0]).is_relative_to(site) and int(cue[1]) > 0
