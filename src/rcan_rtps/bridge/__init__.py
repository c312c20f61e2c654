"""The bridge application: commands → ROS 2, telemetry → STATUS, goals, mDNS, the runtime.

Run through `rcan-rtps run`; to embed it, `Bridge(config).start()` / `.stop()` (its state in
`Bridge.state`). The pieces it is made of are public too: `rcan_rtps.governance`,
`rcan_rtps.api`, `rcan_rtps.ros`.
"""

from .errors import BridgeError, BridgeStateError
from .runtime import Bridge, BridgeOptions, BridgeState

__all__ = ["Bridge", "BridgeError", "BridgeOptions", "BridgeState", "BridgeStateError"]
