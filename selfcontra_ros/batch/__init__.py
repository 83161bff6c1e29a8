"""Batch labeling and training over many inputs on a Ray cluster: ``selfcontra batch label`` / ``batch train``.

DESIGN section 9: the offline entry points are pure functions of their
inputs (:func:`selfcontra_ros.pipeline.label_input`,
:func:`selfcontra_ros.confidence.commands.input_samples`), and this package
only spreads them, one Ray task per input, over a cluster: a local one on this
machine by default, so a laptop and a cluster run the same command.

- :mod:`~selfcontra_ros.batch.inputs`: arguments and globs to named inputs;
- :mod:`~selfcontra_ros.batch.engine`: Ray (local, ``auto``, ``ray://``) or, without Ray, this process;
- :mod:`~selfcontra_ros.batch.label`: :func:`batch_label`, atomic per-input outputs, resume, summary;
- :mod:`~selfcontra_ros.batch.train`: :func:`batch_train`, per-input samples gathered into one forest.

Ray is the optional ``[cluster]`` extra; nothing here imports it before a batch runs.
"""

from selfcontra_ros.batch.inputs import BatchInput, expand_inputs, input_name
from selfcontra_ros.batch.label import batch_label
from selfcontra_ros.batch.train import batch_train

__all__ = ["BatchInput", "batch_label", "batch_train", "expand_inputs", "input_name"]
