"""The bridge application: commands → ROS 2, telemetry → STATUS, goals, mDNS, the runtime.

Run through `rcan-rtps run`; to embed it, `Bridge(config).start()` / `.stop()` (its state in
`Bridge.state`). The pieces it is made of are public too: `rcan_rtps.governance`,
`rcan_rtps.api`, `rcan_rtps.ros`.
"""

from typing import TYPE_CHECKING, Any

from .errors import BridgeError, BridgeStateError

if TYPE_CHECKING:
    from .runtime import Bridge, BridgeOptions, BridgeState

__all__ = ["Bridge", "BridgeError", "BridgeOptions", "BridgeState", "BridgeStateError"]


def __getattr__(name: str) -> Any:
    # The runtime (aiohttp, cyclonedds, …) on first use: `rcan-rtps run` loads its config
    # before, so the YAML loader's memory is released before they are imported.
    if name in ("Bridge", "BridgeOptions", "BridgeState"):
        from . import runtime

        return getattr(runtime, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
