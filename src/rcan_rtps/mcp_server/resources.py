"""The MCP resources: what an agent may read of the robot, each one request to its bridge.

- `robot://status`: STATUS as GET /api/status answers it;
- `robot://telemetry`: a snapshot of the robot's body — state, e-stop, pose, velocity, joints,
  battery, faults and the navigation in progress — from that same STATUS;
- `robot://safety-manifest`: the limits, workspace and e-stop every command is held to;
- `robot://audit/mine`: the agent's own newest audit entries (GET /api/audit/mine): what it
  asked, what came of it, with its model and thought ids. Never another principal's;
- `robot://image/{name}`: a configured camera's newest frame (GET /api/images/{name}), a PNG
  (or the JPEG the camera sent), listed for each camera the bridge has.

No MCP SDK import here (the server turns these into the SDK's types).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any

from .ports import Reply, RobotApi

JSON_TYPE = "application/json"
RESOURCE_NOT_FOUND = -32002  # MCP's code for a resource that is not there
MY_AUDIT_LAST = 50
IMAGE_PREFIX = "robot://image/"
IMAGE_TEMPLATE = IMAGE_PREFIX + "{name}"
IMAGE_DESCRIPTION = ("The newest frame of the robot's camera `{name}`: a PNG (a raw frame, "
                     "shown losslessly) or the JPEG the camera sent.")
TELEMETRY_FIELDS = ("state", "estop", "battery_pct", "battery_v", "telemetry", "position",
                    "faults", "navigation", "active_goals", "foreign_publishers",
                    "foreign_publishers_count", "timestamp_ms")


def _as_is(body: dict[str, Any]) -> Any:
    return body


def _telemetry(body: dict[str, Any]) -> Any:
    return {k: body[k] for k in TELEMETRY_FIELDS if k in body}


@dataclass(frozen=True)
class ResourceDef:
    uri: str
    name: str
    description: str
    read: Callable[[RobotApi], Awaitable[Reply]]
    shape: Callable[[dict[str, Any]], Any] = _as_is


async def _my_audit(api: RobotApi) -> Reply:
    return await api.my_audit(MY_AUDIT_LAST)


RESOURCES: Mapping[str, ResourceDef] = {r.uri: r for r in (
    ResourceDef("robot://status", "status",
                "The robot's STATUS now: state, e-stop, pose, velocity, battery, faults, "
                "active goals, approvals waiting, the ROS graph's health.",
                lambda api: api.status()),
    ResourceDef("robot://telemetry", "telemetry",
                "A snapshot of the robot's body: state, e-stop, pose (m, rad), velocity "
                "(m/s, rad/s), joints, battery (%, V), faults, the navigation in progress, other "
                "publishers on the robot's command topics.",
                lambda api: api.status(), _telemetry),
    ResourceDef("robot://safety-manifest", "safety manifest",
                "The limits every command is held to (speeds, durations, accelerations), the "
                "workspace polygon, the e-stop and who may clear it, the audit log's health.",
                lambda api: api.safety_manifest()),
    ResourceDef("robot://audit/mine", "my audit entries",
                f"Your own newest audit entries (at most {MY_AUDIT_LAST}), oldest first: "
                "each command you sent, its outcome and reason, with your model and thought "
                "id, hash-chained and signed by the bridge.", _my_audit),
)}
