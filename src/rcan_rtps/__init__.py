"""rcan-rtps: RCAN governance in front of a ROS 2 robot, as a plain DDS peer."""

__version__ = "0.1.0"
