"""The inputs of a batch: command-line paths and globs expanded to one entry per bag or sequence, each named once.

An argument may be

- a rosbag2 bag (folder with ``metadata.yaml``, or an ``.mcap`` file);
- a KITTI-layout sequence folder (``ROOT/sequences/XX`` with ``image_0``/``image_1``);
- a KITTI odometry root (``ROOT`` with ``sequences/``): one entry per sequence in it
  (a root holding one sequence is kept as given, as ``selfcontra label ROOT`` takes it);
- a glob (``bags/*.mcap``, ``recordings/2026-*``), expanded in sorted order; a glob
  matching nothing is an error, as is a plain path that does not exist.

Each entry's **name** is its output folder below ``OUT_DIR``: a bag folder's
name, an ``.mcap`` file's stem, ``<root name>_<XX>`` for sequence ``XX`` of a
root (whether the root or the ``sequences/XX`` folder was given, so both spell
the same name). Two entries with one name are refused: their outputs would
collide. The same input given twice counts once.
"""

from __future__ import annotations

import glob
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from selfcontra_ros.errors import BatchError
from selfcontra_ros.pipeline import BAG, SEQUENCE, input_kind

__all__ = ["BatchInput", "expand_inputs", "input_name"]

_GLOB_CHARS = frozenset("*?[")


@dataclass(frozen=True)
class BatchInput:
    """One unit of work of a batch: a bag or one sequence.

    Attributes:
        path: the bag or sequence folder, as given (or as the glob or root expansion found it).
        name: its output folder below ``OUT_DIR`` (module docstring).
        kind: ``"bag"`` or ``"sequence"`` (:func:`selfcontra_ros.pipeline.input_kind`).
    """

    path: Path
    name: str
    kind: str


def input_name(path: Path | str) -> str:
    """The output name of a bag or a sequence folder (module docstring)."""
    path = Path(path)
    if input_kind(path) == BAG:
        return path.stem if path.is_file() else path.name
    if path.parent.name == "sequences":
        return f"{path.parent.parent.resolve().name}_{path.name}"
    sequences = _sequence_folders(path)
    if len(sequences) == 1:
        return f"{path.resolve().name}_{sequences[0].name}"
    return path.resolve().name


def _sequence_folders(root: Path) -> list[Path]:
    """The sequence folders of an odometry root (none when ``root`` is not one)."""
    if not (root / "sequences").is_dir():
        return []
    return sorted(p for p in (root / "sequences").iterdir() if p.is_dir())


def _expand_one(argument: str) -> list[Path]:
    if any(c in _GLOB_CHARS for c in argument):
        matches = sorted(glob.glob(argument))  # noqa: PTH207 (Path.glob takes no absolute pattern)
        if not matches:
            raise BatchError(f"input pattern {argument!r} matches nothing")
        paths = [Path(m) for m in matches]
    else:
        path = Path(argument)
        if not path.exists():
            raise BatchError(f"input {argument} does not exist (expected a bag, a sequence folder or an odometry root)")
        paths = [path]
    expanded: list[Path] = []
    for path in paths:
        if input_kind(path) == SEQUENCE and (path / "sequences").is_dir():
            sequences = _sequence_folders(path)
            if not sequences:
                raise BatchError(f"odometry root {path} holds no sequence folder in {path / 'sequences'}")
            # A root with one sequence stays as given (as 'selfcontra label ROOT' takes it); several: one each.
            expanded.extend([path] if len(sequences) == 1 else sequences)
        else:
            expanded.append(path)
    return expanded


def expand_inputs(arguments: Iterable[str | Path]) -> list[BatchInput]:
    """The batch's inputs, in the order given (globs sorted), each once.

    A path that is neither a bag nor a sequence folder is kept: labelling it
    fails with the labeler's own error, reported for that input alone.

    Raises:
        BatchError: no argument, a path that does not exist, a glob matching nothing, an odometry
            root without sequences, or two inputs with the same output name.
    """
    found: list[BatchInput] = []
    seen: set[Path] = set()
    names: dict[str, Path] = {}
    for argument in arguments:
        for path in _expand_one(str(argument)):
            sequences = _sequence_folders(path)
            resolved = (sequences[0] if len(sequences) == 1 else path).resolve()  # a root is its one sequence
            if resolved in seen:
                continue
            seen.add(resolved)
            name = input_name(path)
            if name in names:
                raise BatchError(
                    f"inputs {names[name]} and {path} would both write OUT_DIR/{name}; "
                    "label them in separate batches (another --out)"
                )
            names[name] = path
            found.append(BatchInput(path=path, name=name, kind=input_kind(path)))
    if not found:
        raise BatchError("no input given: name bags, sequence folders or odometry roots (globs allowed)")
    return found
