"""Reading and writing rosbag2 MCAP bags without a ROS install."""
