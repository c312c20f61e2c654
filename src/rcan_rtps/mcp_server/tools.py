"""The MCP tools, derived: one per action of the registry, and the reads an agent needs.

An action's tool takes the action's parameters as they are (its input schema is the JSON
Schema msgspec makes of the action's params struct, with its limits), plus what the agent
states about the call itself: its `confidence` and `reasoning`. A new action in the registry
is a new tool, with no code here.

A streamed action (a velocity held on the wire, like `move`) is timed for an agent: its
`duration_s` is required, so nothing an agent starts runs on until someone stops it. A
streamed action that cannot be timed (no `duration_s` parameter) is not offered at all.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import msgspec

from rcan_rtps.rcan.actions import ActionSpec, Invariant, specs

DURATION = "duration_s"
PENDING_ID = {"type": "string", "minLength": 1, "maxLength": 64, "pattern": "^[A-Za-z0-9_-]+$",
              "description": "the `pending_id` a gated command returned (pending_auth)"}
# What the agent states about a call, beside the action's parameters (RCAN §16 AI fields).
AI_ARGUMENTS: Mapping[str, dict[str, Any]] = {
    "confidence": {
        "type": "number", "minimum": 0.0, "maximum": 1.0,
        "description": "Your confidence in this command, 0 to 1. Below the robot's confidence "
                       "gate the command waits for a human; none stated counts as 0."},
    "reasoning": {
        "type": "string", "maxLength": 8192,
        "description": "Why you send this command: kept in the bridge's thought log (readable "
                       "by its owners), its SHA-256 in the signed audit log."},
}
WAIT_MAX_S = 600.0
# The robot's limits (its safety manifest's `limits`) each check holds an action to, with
# their units: an action's description states those of its checks, so a new action is
# described with no code here.
LIMITS: Mapping[Invariant, tuple[tuple[str, str], ...]] = {
    Invariant.VELOCITY: (("max_linear_vel", "m/s"), ("max_angular_vel", "rad/s")),
    Invariant.DURATION: (("max_move_duration_s", "s"),),
    Invariant.ACCELERATION: (("max_linear_accel", "m/s²"), ("max_angular_accel", "rad/s²")),
}


@dataclass(frozen=True)
class ToolDef:
    """One tool as MCP lists it; `action` is the registry's spec for an action's tool."""

    name: str
    description: str
    input_schema: dict[str, Any]
    action: ActionSpec[Any] | None = None

    @property
    def timed(self) -> bool:
        """An agent must give `duration_s`, and the server heartbeats while it runs."""
        return self.action is not None and self.action.streamed


def params_schema(params: type[Any]) -> dict[str, Any]:
    """The JSON Schema of a params struct with the struct itself at the root (MCP wants
    `type: object` there); structs it refers to stay in `$defs`."""
    schema = msgspec.json.schema(params)
    defs = dict(schema.pop("$defs", {}))
    ref = schema.get("$ref")
    root = dict(defs.pop(ref.rsplit("/", 1)[1])) if isinstance(ref, str) else schema
    root.pop("title", None)
    if defs:
        root["$defs"] = defs
    return root


def _required(prop: dict[str, Any]) -> dict[str, Any]:
    """An optional property's schema as a required one: its non-null branch, no default."""
    branches = [b for b in prop.get("anyOf", ()) if b != {"type": "null"}]
    kept = {k: v for k, v in prop.items() if k not in ("anyOf", "default")}
    return {**branches[0], **kept} if len(branches) == 1 else kept


def _limits_line(spec: ActionSpec[Any], manifest: Mapping[str, Any]) -> str | None:
    """This robot's limits on the action, from its safety manifest (None: none apply)."""
    limits = manifest.get("limits") or {}
    said = [f"{name} {limits[name]:g} {unit}" for check in spec.invariants
            for name, unit in LIMITS.get(check, ()) if isinstance(limits.get(name), int | float)]
    if Invariant.VELOCITY in spec.invariants and said:
        over = ("refused" if limits.get("velocity_exceed_deny", True)
                else "clamped to the limit")
        said.append(f"a velocity up to 10 % over is clamped to the limit, beyond that {over}")
    workspace = manifest.get("workspace")
    if Invariant.WORKSPACE in spec.invariants and isinstance(workspace, dict):
        corners = " ".join(f"({x:g}, {y:g})" for x, y in workspace.get("polygon", ()))
        said.append(f"the goal must lie inside the workspace polygon {corners} "
                    f"(frame {workspace.get('frame_id')}, m)")
    return f"This robot's limits: {'; '.join(said)}." if said else None


def _describe(spec: ActionSpec[Any], manifest: Mapping[str, Any]) -> str:
    facts = spec.describe()
    lines = [spec.summary,
             f"Needs the {facts['default_role']} role or higher (the robot's config may "
             "differ)."]
    if spec.stopping:
        lines.append("Never refused to an authenticated caller, never waits for a human: "
                     "use it whenever the robot must stop.")
    elif facts["hitl"] != "never":
        lines.append("May be held for a human's approval (outcome pending_auth, with a "
                     "pending_id): then call wait_for_approval.")
    if spec.streamed:
        lines.append(f"Timed: `{DURATION}` (seconds) is required, up to the robot's "
                     "safety.max_move_duration_s; this server keeps the control session "
                     "alive while it runs.")
    if spec.starts_goal:
        lines.append("Starts a goal (its goal_id comes back): follow it with get_goals; this "
                     "server keeps the control session alive until it ends.")
    lines.append(f"Checked by: {', '.join(facts['invariants'])}.")
    limits = _limits_line(spec, manifest)
    if limits is not None:
        lines.append(limits)
    return " ".join(lines)


def action_tool(spec: ActionSpec[Any], manifest: Mapping[str, Any] | None = None
                ) -> ToolDef | None:
    """The tool of one registry action; None for a streamed action that cannot be timed.
    `manifest`: the robot's safety manifest, whose limits the description states."""
    schema = params_schema(spec.params)
    props: dict[str, Any] = copy.deepcopy(schema.get("properties", {}))
    required = list(schema.get("required", []))
    clash = sorted(set(props) & set(AI_ARGUMENTS))
    if clash:
        raise ValueError(f"action {spec.name!r}: parameter(s) {clash} clash with what an agent "
                         "states about a call")
    if spec.streamed:
        if DURATION not in props:
            return None
        props[DURATION] = _required(props[DURATION])
        required.append(DURATION)
    for name, prop in props.items():
        if name.endswith("_s") and "description" not in prop:
            prop["description"] = "seconds"
    props.update(copy.deepcopy(dict(AI_ARGUMENTS)))
    schema.update(properties=props, required=sorted(set(required)))
    return ToolDef(spec.name, _describe(spec, manifest or {}), schema, spec)


def _object(properties: dict[str, Any], required: list[str]) -> dict[str, Any]:
    return {"type": "object", "properties": properties, "required": required,
            "additionalProperties": False}


READS = (
    ToolDef("get_status", "The robot's STATUS now: state (idle, moving, safe_stop, ...), "
            "e-stop, pose (telemetry.position in m, yaw in rad), velocity (m/s, rad/s), "
            "battery (%), faults, active goals, pending approvals.", _object({}, [])),
    ToolDef("get_goals", "The goals the bridge tracks (navigation, docking, ...): each with "
            "its state (accepted, executing, succeeded, aborted, canceled, ...), feedback and "
            "result.", _object({}, [])),
    ToolDef("get_my_pending_approvals", "Your commands held for a human right now, each with "
            "its pending_id, the role that must approve it and when it expires.",
            _object({}, [])),
    ToolDef("get_pending_approval", "One of your commands held for a human: `pending` while "
            "it waits (with the role that must approve it and when it expires), then "
            "`resolved` with the decision that ended it (executed, denied, withdrawn, "
            "expired).", _object({"pending_id": PENDING_ID}, ["pending_id"])),
    ToolDef("wait_for_approval", "Wait until a human has decided one of your held commands, "
            "or `timeout_s` has passed: the decision (executed, or why not), or the command "
            "still pending. Other tools (estop, stop) can be called while it waits.",
            _object({"pending_id": PENDING_ID,
                     "timeout_s": {"type": "number", "exclusiveMinimum": 0.0,
                                   "maximum": WAIT_MAX_S, "default": 30.0,
                                   "description": "seconds to wait at most"}},
                    ["pending_id"])),
)


def derive_tools(actions: Iterable[ActionSpec[Any]] | None = None,
                 manifest: Mapping[str, Any] | None = None) -> dict[str, ToolDef]:
    """Every tool by name: the registry's actions (`specs()` unless given), then the reads.
    `manifest`: the robot's safety manifest (its limits go into the descriptions)."""
    tools: dict[str, ToolDef] = {}
    found = [action_tool(spec, manifest) for spec in (specs() if actions is None else actions)]
    for tool in [*(t for t in found if t is not None), *READS]:
        if tool.name in tools:
            raise ValueError(f"two tools named {tool.name!r}")
        tools[tool.name] = tool
    return tools
