"""Make ``docs/synthetic_street.png``: a rendered street frame above its ground-truth disparity.

Run from the repository root: ``python docs/make_synthetic_figure.py [--frame 6] [--seed 1]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from selfcontra_ros.datasets.synthetic import make_scene

OUT = Path(__file__).resolve().parent / "synthetic_street.png"
# Disparity (pixels) mapped to the top of the colour map; larger values saturate.
MAX_DISPARITY = 96.0
# Output width in pixels; the full KITTI width makes a PNG too large for the README.
WIDTH = 920


def main() -> None:
    """Render the frame, colour the disparity (black where there is no ground truth) and write the PNG."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--frame", type=int, default=6)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()

    scene = make_scene("street", args.seed, frames=args.frame + 1)
    frame = scene.render(args.frame)
    disparity = frame.disparity
    has = np.isfinite(disparity)
    scaled = np.clip(np.nan_to_num(disparity) / MAX_DISPARITY * 255.0, 0, 255).astype(np.uint8)
    colour = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    colour[~has] = 0
    left = cv2.cvtColor(frame.left, cv2.COLOR_GRAY2BGR)
    height = round(frame.left.shape[0] * WIDTH / frame.left.shape[1])
    panels = [cv2.resize(p, (WIDTH, height), interpolation=cv2.INTER_AREA) for p in (left, colour)]
    labels = ("left image", f"ground-truth disparity (0-{MAX_DISPARITY:.0f} px, black: none)")
    for panel, label in zip(panels, labels, strict=True):
        cv2.putText(panel, label, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    cv2.imwrite(str(args.out), np.vstack(panels), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} kB)")


if __name__ == "__main__":
    main()
