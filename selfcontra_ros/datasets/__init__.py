"""Dataset readers (KITTI, Middlebury, ETH3D) and the package's own synthetic scenes."""

#: The synthetic scenes of :mod:`selfcontra_ros.datasets.synthetic` (here, so the CLI lists them without numpy).
SCENES = ("street", "orbit", "room", "highway")
