"""Where the package's installed files (``config/``, ``launch/``) live.

The same code runs from three kinds of install, and each puts ``config/``
somewhere else:

1. a colcon workspace (``<prefix>/share/selfcontra_ros/config``, found through
   the ament index),
2. ``pip install .`` into an environment (``<sys.prefix>/share/selfcontra_ros``),
3. a source checkout or ``pip install -e .`` (the repository's ``config/``).

:func:`share_dir` tries them in that order.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from selfcontra_ros.errors import SelfContraError

__all__ = ["PACKAGE", "config_file", "share_dir"]

PACKAGE = "selfcontra_ros"


def _candidates() -> list[Path]:
    found: list[Path] = []
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix and (Path(prefix) / "share/ament_index/resource_index/packages" / PACKAGE).is_file():
            found.append(Path(prefix) / "share" / PACKAGE)
    found.append(Path(sys.prefix) / "share" / PACKAGE)
    found.append(Path(__file__).resolve().parent.parent)  # source checkout / editable install
    return found


def share_dir() -> Path:
    """Return the folder holding ``config/`` (and ``launch/``) for this install."""
    for candidate in _candidates():
        if (candidate / "config").is_dir():
            return candidate
    raise SelfContraError(
        f"cannot find the {PACKAGE} config/ folder; looked in " + ", ".join(str(c) for c in _candidates())
    )


def config_file(name: str) -> Path:
    """Return the path of ``config/<name>`` of this install.

    Raises:
        SelfContraError: if the file does not exist.
    """
    path = share_dir() / "config" / name
    if not path.is_file():
        raise SelfContraError(f"config file {name!r} not found at {path}")
    return path
