"""rcan-rtps: RCAN governance in front of a ROS 2 robot, as a plain DDS peer.

Public packages: `rcan_rtps.ros` (the wire), `rcan_rtps.governance`, `rcan_rtps.rcan`,
`rcan_rtps.config`, `rcan_rtps.api`; each exports its API through `__all__`.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
