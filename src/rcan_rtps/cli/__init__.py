"""The `rcan-rtps` command line, shaped like ros2cli."""
