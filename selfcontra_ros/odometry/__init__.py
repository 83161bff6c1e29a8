"""Stereo visual odometry: poses for sequences and bags that have none."""
