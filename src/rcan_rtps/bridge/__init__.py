"""The bridge application: commands → ROS 2, telemetry → STATUS, goals, mDNS, the runtime.

No public Python API (yet): it is run through `rcan-rtps run`. Embed the pieces it is made of
instead: `rcan_rtps.governance`, `rcan_rtps.api`, `rcan_rtps.ros`.
"""

__all__: list[str] = []
