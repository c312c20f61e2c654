"""The ROS 2 wire layer: a ROS 2 node made of plain DDS. Knows nothing of RCAN.

Public API (the modules stay importable for the finer parts: `names`, `qos`, `rostime`)::

    RosNode(name, namespace, *, domain_id=, localhost=, distro=, idl_paths=,
            max_sample_bytes=)                                             context manager
      .create_publisher(topic, type) -> RosPublisher
      .create_subscription(topic, type) -> RosSubscription   (async get / async for)
    ServiceClient / ServiceServer, ActionClient / ActionServer   over both request mappings
    RosGraph                 topics, nodes, services and actions seen through DDS discovery
    TypeStore                one definition per ROS type, loaded from IDL; RIHS01 hashes
    serialize / deserialize  messages to and from CDR bytes, no DDS (like rclpy.serialization)
    QosProfile               ROS QoS, with `qos.preset(name)` for the named profiles
    WireError and its tree   see `errors`

Importing it checks the installed cyclonedds binding first (`_binding`): on one that cannot
run it (the 0.10 line) the import raises UnsupportedBindingError, saying how to get 11.x.
"""

import importlib
from typing import TYPE_CHECKING, Any

from ._binding import require_supported_binding

require_supported_binding()  # before the modules below touch what a 0.10 binding lacks

from .errors import (
    ActionError,
    AmbiguousReply,
    CdrDecodeError,
    GraphTimeout,
    IdlSyntaxError,
    InvalidNameError,
    QosError,
    SampleTooLarge,
    ServiceTimeout,
    ServiceUnavailable,
    UnknownTypeError,
    UnsupportedBindingError,
    UnsupportedDistroError,
    UnsupportedTypeError,
    ValueFitError,
    WireError,
)

if TYPE_CHECKING:
    from .action_goals import ClientGoal, GoalResult
    from .action_server import ActionServer, ServerGoal
    from .actions import ActionClient, GoalState
    from .graph import Direction, Endpoint, RosGraph
    from .participant import RosNode, RosPublisher, RosSubscription
    from .qos import Durability, History, QosProfile, Reliability
    from .serialization import Codec, deserialize, serialize
    from .service_server import ServiceServer
    from .services import RequestMapping, ServiceClient
    from .typesys import TypeStore

# The rest of the public names, each imported with its module on first use (PEP 562): a
# process that needs topics only (a bridge run whose config names no goal server, `topic
# echo`) never loads the services and actions (issue 27: idle memory).
_LAZY = {
    **dict.fromkeys(("ActionClient", "GoalState"), "actions"),
    **dict.fromkeys(("ClientGoal", "GoalResult"), "action_goals"),
    **dict.fromkeys(("ActionServer", "ServerGoal"), "action_server"),
    **dict.fromkeys(("Direction", "Endpoint", "RosGraph"), "graph"),
    **dict.fromkeys(("RosNode", "RosPublisher", "RosSubscription"), "participant"),
    **dict.fromkeys(("Durability", "History", "QosProfile", "Reliability"), "qos"),
    **dict.fromkeys(("Codec", "deserialize", "serialize"), "serialization"),
    **dict.fromkeys(("RequestMapping", "ServiceClient"), "services"),
    "ServiceServer": "service_server",
    "TypeStore": "typesys",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # once: later reads are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = [
    "ActionClient",
    "ActionError",
    "ActionServer",
    "AmbiguousReply",
    "CdrDecodeError",
    "ClientGoal",
    "Codec",
    "Direction",
    "Durability",
    "Endpoint",
    "GoalResult",
    "GoalState",
    "GraphTimeout",
    "History",
    "IdlSyntaxError",
    "InvalidNameError",
    "QosError",
    "QosProfile",
    "Reliability",
    "RequestMapping",
    "RosGraph",
    "RosNode",
    "RosPublisher",
    "RosSubscription",
    "SampleTooLarge",
    "ServerGoal",
    "ServiceClient",
    "ServiceServer",
    "ServiceTimeout",
    "ServiceUnavailable",
    "TypeStore",
    "UnknownTypeError",
    "UnsupportedBindingError",
    "UnsupportedDistroError",
    "UnsupportedTypeError",
    "ValueFitError",
    "WireError",
    "deserialize",
    "serialize",
]
