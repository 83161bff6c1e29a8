"""ROS 2 adapters: message conversion and nodes (the only place that imports rclpy)."""
