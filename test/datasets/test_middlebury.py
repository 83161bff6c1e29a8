"""Middlebury 2014 (MiddEval3) and ETH3D two-view folders: PFM, calib.txt, masks, and train / evaluate on them.

The folders are made here from a synthetic scene (``../shared/data`` has none):
a colour MiddEval3-style scene with ``mask0nocc.png`` and a grey ETH3D-style
one without, each with a little-endian or big-endian PFM.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from selfcontra_ros.cli import main
from selfcontra_ros.confidence.commands import evaluate_command, iter_frames, train_command
from selfcontra_ros.datasets.middlebury import (
    is_middlebury_scene,
    middlebury_scenes,
    read_calibration,
    read_middlebury,
    read_pfm,
)
from selfcontra_ros.datasets.synthetic import make_scene
from selfcontra_ros.errors import DatasetError

WIDTH, HEIGHT = 320, 96
OCCLUDED, NO_GT = 128, 0


def write_pfm(path: Path, image: NDArray[np.float32], *, little_endian: bool = True) -> None:
    """A grey PFM as the benchmarks write it: rows bottom to top, scale sign = byte order."""
    dtype = "<f4" if little_endian else ">f4"
    header = f"Pf\n{image.shape[1]} {image.shape[0]}\n{-1.0 if little_endian else 1.0}\n".encode()
    path.write_bytes(header + np.ascontiguousarray(image[::-1], dtype=dtype).tobytes())


def write_calib(path: Path, fx: float, cx0: float, cx1: float, cy: float, baseline_mm: float, ndisp: int) -> None:
    path.write_text(
        f"cam0=[{fx} 0 {cx0}; 0 {fx} {cy}; 0 0 1]\n"
        f"cam1=[{fx} 0 {cx1}; 0 {fx} {cy}; 0 0 1]\n"
        f"doffs={cx1 - cx0}\nbaseline={baseline_mm}\nwidth={WIDTH}\nheight={HEIGHT}\nndisp={ndisp}\n"
        "isint=0\nvmin=1\nvmax=60\ndyavg=0\ndymax=0\n"
    )


def make_scene_folder(root: Path, name: str, seed: int, *, color: bool, mask: bool, little_endian: bool) -> Path:
    """One scene folder; returns it. ``gt.npy`` beside it holds the expected ground truth (NaN = none)."""
    scene = make_scene("street", seed, WIDTH, HEIGHT, frames=4)
    frame = scene.render(1)
    folder = root / name
    folder.mkdir(parents=True)
    for file, image in (("im0.png", frame.left), ("im1.png", frame.right)):
        written = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if color else image
        assert cv2.imwrite(str(folder / file), written)
    camera = scene.camera
    write_calib(folder / "calib.txt", camera.fx, camera.cx, camera.cx, camera.cy, camera.baseline * 1000.0, 64)
    gt = np.where(np.isfinite(frame.disparity), frame.disparity, np.inf).astype(np.float32)
    write_pfm(folder / "disp0GT.pfm", gt, little_endian=little_endian)
    expected = np.where(np.isfinite(gt), gt, np.nan).astype(np.float32)
    if mask:
        labels = np.full((HEIGHT, WIDTH), 255, np.uint8)
        labels[:, :40] = OCCLUDED  # a band "occluded in the right view"
        labels[~np.isfinite(frame.disparity)] = NO_GT
        assert cv2.imwrite(str(folder / "mask0nocc.png"), labels)
        expected[labels != 255] = np.nan
    np.save(root / f"{name}.gt.npy", expected)
    return folder


@pytest.fixture(scope="module")
def benchmark(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("middeval3")
    make_scene_folder(root, "Adirondack", 1, color=True, mask=True, little_endian=True)
    make_scene_folder(root, "delivery_area_1l", 2, color=False, mask=False, little_endian=False)
    return root


def test_pfm_round_trips_in_both_byte_orders(tmp_path: Path) -> None:
    image = np.arange(12, dtype=np.float32).reshape(3, 4) * 0.5
    image[0, 0] = np.inf
    for little in (True, False):
        write_pfm(tmp_path / "d.pfm", image, little_endian=little)
        read = read_pfm(tmp_path / "d.pfm")
        assert read.dtype == np.float32 and read.shape == (3, 4)
        assert np.array_equal(read, image)  # first row at the top, inf kept


def test_malformed_pfm_and_calib_are_named(tmp_path: Path) -> None:
    (tmp_path / "bad.pfm").write_bytes(b"P5\n4 3\n255\n" + bytes(12))
    with pytest.raises(DatasetError, match="not a PFM"):
        read_pfm(tmp_path / "bad.pfm")
    (tmp_path / "colour.pfm").write_bytes(b"PF\n4 3\n-1.0\n" + bytes(144))
    with pytest.raises(DatasetError, match="colour PFM"):
        read_pfm(tmp_path / "colour.pfm")
    write_pfm(tmp_path / "short.pfm", np.zeros((3, 4), np.float32))
    (tmp_path / "short.pfm").write_bytes((tmp_path / "short.pfm").read_bytes()[:-8])
    with pytest.raises(DatasetError, match="header needs 48"):
        read_pfm(tmp_path / "short.pfm")
    (tmp_path / "calib.txt").write_text("cam0=[1 0 2; 0 1 3; 0 0 1]\ncam1=[1 0 2; 0 1 3; 0 0 1]\n")
    with pytest.raises(DatasetError, match="lacks baseline"):
        read_calibration(tmp_path / "calib.txt")


def test_scenes_read_with_their_ground_truth_and_masks(benchmark: Path) -> None:
    scenes = middlebury_scenes(benchmark)
    assert [s.name for s in scenes] == ["Adirondack", "delivery_area_1l"] and all(map(is_middlebury_scene, scenes))
    colour, grey = (read_middlebury(s) for s in scenes)
    assert colour.left.shape == (HEIGHT, WIDTH, 3) and grey.left.shape == (HEIGHT, WIDTH)
    for frame in (colour, grey):
        expected = np.load(benchmark / f"{frame.name}.gt.npy")
        assert frame.gt_disparity is not None
        assert np.array_equal(frame.gt_disparity, expected, equal_nan=True)
    # "all" ignores the mask: the occluded band gets its ground truth back, unknown pixels stay NaN.
    every = read_middlebury(scenes[0], ground_truth="all").gt_disparity
    assert every is not None and np.isfinite(every[:, :40]).any()
    assert np.isnan(every).sum() < np.isnan(colour.gt_disparity).sum()  # type: ignore[arg-type]
    calib = read_calibration(scenes[0] / "calib.txt")
    assert calib.baseline == pytest.approx(make_scene("street", 1, WIDTH, HEIGHT, frames=2).camera.baseline)
    d = np.array([10.0, 20.0], np.float32)
    np.testing.assert_allclose(calib.depth(d), calib.baseline * calib.fx / (d + calib.doffs), rtol=1e-6)


def test_a_test_split_scene_has_no_ground_truth(benchmark: Path, tmp_path: Path) -> None:
    scene = tmp_path / "Australia"
    scene.mkdir()
    for name in ("im0.png", "im1.png", "calib.txt"):
        (scene / name).write_bytes((benchmark / "Adirondack" / name).read_bytes())
    frame = read_middlebury(scene)
    assert frame.gt_disparity is None and frame.left.shape == (HEIGHT, WIDTH, 3)


def test_train_and_evaluate_read_the_benchmark_folders(benchmark: Path, tmp_path: Path) -> None:
    frames = list(iter_frames(benchmark))
    assert [f.name for f in frames] == ["Adirondack", "delivery_area_1l"]
    model = tmp_path / "ensemble.npz"
    summary = train_command([(benchmark, "gt")], "ensemble", model, forest={"n_estimators": 4, "min_samples_leaf": 5})
    assert summary["frames"] == 2 and model.is_file()
    results = evaluate_command([model, "lrd"], benchmark, tmp_path / "eval")
    names = [n for n in results if n != "table"]
    assert len(names) == 2
    for name in names:
        frames_scored = results[name]["frames"]
        assert len(frames_scored) == 2 and all(np.isfinite(f["ausc_ratio"]) for f in frames_scored)
    assert json.loads((tmp_path / "eval" / "summary.json").read_text())


def test_cli_trains_and_evaluates_on_the_benchmark_folders(
    benchmark: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = tmp_path / "park.model"
    status = main(["train", "--features", "park", "--data", str(benchmark), "--labels", "gt", "--out", str(model)])
    assert status == 0
    assert model.is_file() and not (tmp_path / "park.model.npz").exists()  # the path given, no .npz added
    printed = capsys.readouterr().out
    assert "from 2 frames" in printed and printed.rstrip().endswith(str(model))
    out = tmp_path / "eval"
    args = ["evaluate-confidence", "--model", str(model), "--model", "lrd", "--model", "wls"]
    assert main([*args, "--data", str(benchmark), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    for name in ("park", "lrd", "wls"):
        assert f"{name}: AUSC " in printed
        record = json.loads((out / name / "metrics.json").read_text())
        assert [f["frame"] for f in record["frames"]] == ["Adirondack", "delivery_area_1l"]
        assert all(f["ausc_ratio"] >= 1.0 - 1e-9 for f in record["frames"])
    table = (out / "table.md").read_text().splitlines()
    assert table[0] == "| training source | LRD | WLS | Ensemble | Park | GCP |"
    cells = [c.strip() for c in table[2].strip("|").split("|")]
    assert cells[0] == "ground truth" and cells[3] == "-" and cells[5] == "-"
    assert all(float(cells[i]) >= 1.0 for i in (1, 2, 4))
    # One ETH3D scene folder on its own is a data set too.
    alone = tmp_path / "eth3d"
    assert (
        main(
            [
                "evaluate-confidence",
                "--model",
                "wls",
                "--data",
                str(benchmark / "delivery_area_1l"),
                "--out",
                str(alone),
            ]
        )
        == 0
    )
    record = json.loads((alone / "metrics.json").read_text())
    assert [f["frame"] for f in record["frames"]] == ["delivery_area_1l"]


def test_cli_model_names_as_train_wrote_them(
    benchmark: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """'train --out NAME' writes NAME.npz; evaluate-confidence --model NAME finds it; a missing model is named."""
    bare = tmp_path / "gcp"
    assert (
        main(
            [
                "train",
                "--features",
                "gcp",
                "--data",
                str(benchmark / "Adirondack"),
                "--labels",
                "gt",
                "--out",
                str(bare),
            ]
        )
        == 0
    )
    assert (tmp_path / "gcp.npz").is_file() and not bare.exists()
    assert (
        main(["evaluate-confidence", "--model", str(bare), "--data", str(benchmark), "--out", str(tmp_path / "e")]) == 0
    )
    capsys.readouterr()
    missing = tmp_path / "absent.model"
    assert (
        main(["evaluate-confidence", "--model", str(missing), "--data", str(benchmark), "--out", str(tmp_path / "f")])
        == 2
    )
    assert f"model file {missing} does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "model file to write, as given (.npz is added only to a name without suffix)" in help_text
    with pytest.raises(SystemExit):
        main(["evaluate-confidence", "--help"])
    assert "'wls' (OpenCV's WLS filter confidence" in " ".join(capsys.readouterr().out.split())
