"""Dataset readers (KITTI) and the package's own synthetic scenes."""
