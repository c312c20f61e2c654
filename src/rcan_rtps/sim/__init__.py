"""The simulated robot (a real ROS 2 node over plain DDS), run by `rcan-rtps sim` and `run --sim`.

No public Python API: use the command line.
"""

__all__: list[str] = []
