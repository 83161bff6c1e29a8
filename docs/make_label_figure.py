"""Make a README figure: a sequence's left image above the colour label image of the same frame.

Run from the repository root after ``selfcontra label SEQ --out OUT``::

    python docs/make_label_figure.py SEQ OUT --frame 25 --out docs/kitti06_labels.png

Green: positive (consistent depth), red: negative (contradicting), blue: unknown.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from selfcontra_ros.datasets.kitti import open_sequence
from selfcontra_ros.labels import colorize_labels

# Output width in pixels; the full KITTI width makes a PNG too large for the README.
WIDTH = 720


def main() -> None:
    """Stack the left image and its colour labels (blended over the image) and write the PNG."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequence", type=Path, help="the labelled sequence folder")
    parser.add_argument("labels", type=Path, help="the output folder of `selfcontra label`")
    parser.add_argument("--frame", type=int, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    frame = open_sequence(args.sequence)[args.frame]
    labels = cv2.imread(str(args.labels / "labels" / f"{args.frame:06d}.png"), cv2.IMREAD_UNCHANGED)
    if labels is None:
        raise SystemExit(f"no label image for frame {args.frame} in {args.labels / 'labels'}")
    grey = frame.left if frame.left.ndim == 2 else cv2.cvtColor(frame.left, cv2.COLOR_RGB2GRAY)
    image = np.repeat(grey[:, :, None], 3, axis=2)
    blended = (0.45 * image + 0.55 * colorize_labels(labels)).astype(np.uint8)
    height = round(grey.shape[0] * WIDTH / grey.shape[1])
    panels = [cv2.resize(p, (WIDTH, height), interpolation=cv2.INTER_AREA) for p in (image, blended)]
    figure = np.vstack(panels)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(args.out), cv2.cvtColor(figure, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        raise SystemExit(f"cannot write {args.out}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
