"""Exception classes of selfcontra_ros.

Every error the package raises on bad input derives from
:class:`SelfContraError`, so callers (the ROS nodes, the command line) can
catch the package's own complaints without hiding programming errors.
"""

from __future__ import annotations

__all__ = [
    "BatchError",
    "CalibrationError",
    "ConversionError",
    "DatasetError",
    "PoseError",
    "SelfContraError",
    "TransformError",
]


class SelfContraError(Exception):
    """Base class of all errors raised by selfcontra_ros on bad input."""


class BatchError(SelfContraError):
    """A batch of inputs cannot be run: no input matched, two inputs share an output name, a result exists already."""


class CalibrationError(SelfContraError):
    """Camera calibration is missing, not rectified or inconsistent."""


class ConversionError(SelfContraError):
    """A ROS message cannot be converted to or from a numpy array."""


class DatasetError(SelfContraError):
    """A dataset folder or file is missing or malformed."""


class PoseError(SelfContraError):
    """A pose, rotation or quaternion is not finite or not rigid."""


class TransformError(SelfContraError):
    """A transform between two frames is unknown, or not known at the stamp asked for (TF lookups).

    Attributes:
        reason: short machine-readable cause, used as a drop counter's key
            (e.g. ``tf_unknown_frame``, ``tf_not_connected``, ``tf_after_buffer``).
    """

    def __init__(self, message: str, reason: str = "tf_lookup_failed") -> None:
        super().__init__(message)
        self.reason = reason
