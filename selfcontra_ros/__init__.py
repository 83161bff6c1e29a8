"""selfcontra_ros: stereo confidence labels from self-contradiction.

The algorithm (geometry, the view window, the three labelling stages,
matching, confidence features, metrics) is a plain library with no ROS
import; ROS nodes, bag tools, dataset readers and the command line are thin
adapters around it (``selfcontra_ros.ros``, ``selfcontra_ros.bags``,
``selfcontra_ros.datasets``, ``selfcontra_ros.cli``).
"""

__version__ = "0.1.0"
