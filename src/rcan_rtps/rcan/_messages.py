"""msgspec schemas of the RCAN messages rcan-rtps speaks (see docs/rcan-profile)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Annotated, Any, Literal

import msgspec

from ._enums import RoleName
from ._types import ActionParams, Confidence, MessageId, ShortText, Strict, TimestampMs
from ._v3 import Envelope, Status3, VersionText
from .actions import ActionName, ActionSpec, action_spec

# The model's reasoning behind a command (§16.5's Thought log): kept out of the audit entry
# (which records its digest), readable only with the config scope (see governance/thoughts).
Reasoning = Annotated[str, msgspec.Meta(max_length=8192)]


class AiInfo(Strict, frozen=True):
    provider: ShortText | None = None
    model: ShortText | None = None
    confidence: Confidence | None = None
    thought_id: ShortText | None = None
    reasoning: Reasoning | None = None
    # The software that relayed the model's call (an MCP client: `name/version`): audited.
    client: ShortText | None = None


# -- COMMAND, as it arrives -----------------------------------------------------------------


class ShortCommand(Strict, frozen=True):
    """The bridge spec's short form."""

    action: ActionName
    params: dict[str, Any] = msgspec.field(default_factory=dict)
    message_id: MessageId | None = None
    ai_provider: ShortText | None = None
    ai_model: ShortText | None = None
    confidence: Confidence | None = None
    thought_id: ShortText | None = None
    ai_reasoning: Reasoning | None = None
    ai_client: ShortText | None = None


class EnvelopeCommand(Strict, frozen=True):
    """The RCAN envelope form (message_type 1 = COMMAND)."""

    message_type: Literal[1]
    ruri: Annotated[str, msgspec.Meta(max_length=512)]
    action: ActionName
    parameters: dict[str, Any] = msgspec.field(default_factory=dict)
    message_id: MessageId | None = None
    timestamp_ms: TimestampMs | None = None
    priority: Annotated[int, msgspec.Meta(ge=0, le=255)] = 0
    ai: AiInfo | None = None
    rcan_version: VersionText | None = None  # present: §3.5 applies (see `_v3`)


class Approval(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    """One human's word on a held command (§9): who, in what role, what they decided, why."""

    principal: str
    role: RoleName
    decision: Literal["approve", "deny", "withdraw"]
    at_ms: int
    reason: str | None = None
    message_id: str | None = None  # the AUTHORIZE message (§16.4) that said it, if one did
    # That message's signature, as its audit entry records one: {alg, kid, verified}.
    sig: dict[str, Any] | None = None


class SafetyMessage(Strict, frozen=True):
    """RCAN SAFETY (message_type 6), as the official `rcan` SDK builds it (`rcan.safety`):
    ESTOP and STOP are the e-stop and `stop`; RESUME clears an e-stop (OWNER, like
    `clear_estop`)."""

    message_type: Literal[6]
    safety_event: Literal["ESTOP", "STOP", "RESUME"]
    ruri: Annotated[str, msgspec.Meta(max_length=512)]
    reason: Annotated[str, msgspec.Meta(max_length=512)] | None = None
    timestamp_ms: TimestampMs | None = None
    message_id: MessageId | None = None
    rcan_version: VersionText | None = None  # the SDK leaves it out; present: §3.5 applies


class NormalizedCommand(msgspec.Struct, frozen=True, kw_only=True):
    """The one internal command every form becomes."""

    action: ActionName
    params: ActionParams
    requested: dict[str, Any]
    message_id: str
    client_message_id: bool = False  # the client chose `message_id` (so it may retry with it)
    ruri: str | None = None
    timestamp_ms: int | None = None
    priority: int = 0
    ai: AiInfo | None = None
    claimed_role: Any = None
    # What was wrong with a stop that was executed anyway (audited, and in its reply).
    warnings: tuple[str, ...] = ()
    # Who reviewed it while it was held for a human (§9), in order; set by the governor only
    # (never decoded from a body), and recorded in the audit entries of its resolution.
    approvals: tuple[Approval, ...] = ()
    # A message of the RCAN 3.x generation: what it carried beyond the command (`_v3`).
    envelope: Envelope | None = None
    # The id its goal is sent with (a command that starts one): chosen by the governor before
    # its write-ahead entry, which records it, so a restart after a crash can cancel the goal
    # by id. Set by the governor only (never decoded from a body).
    goal_id: str | None = None

    @property
    def spec(self) -> ActionSpec[Any]:
        """The registry's declaration of this command's action."""
        return action_spec(self.action)


# -- responses and notifications ------------------------------------------------------------


class DecisionBody(msgspec.Struct, omit_defaults=True, kw_only=True):
    """Body of every command / HiTL response."""

    outcome: Literal["executed", "pending_auth", "denied", "safety_violation", "failed"]
    audit_id: str | None = None
    message_id: str | None = None
    error_code: str | None = None
    reason: str | None = None
    applied: dict[str, Any] | None = None
    pending_id: str | None = None
    expires_at_ms: int | None = None
    goal_id: str | None = None  # navigate: follow it at GET /api/goals/{goal_id}
    ros2_topic: str | None = None  # where the command went on the ROS 2 graph
    warnings: list[str] | None = None  # a stop executed although its body had these problems
    # Replies to RCAN 3.x messages (rcan.message.RCANResponse): the message's id, and `outcome`
    # as its status (executed → ok, pending_auth → pending, denied or safety_violation →
    # blocked, failed → error).
    msg_id: str | None = None
    status: Status3 | None = None


class ErrorBody(msgspec.Struct, omit_defaults=True, kw_only=True):
    """Body of a request refused before any decision (e.g. 400, 401, 413)."""

    outcome: Literal["denied", "failed"]  # no default: omit_defaults would drop it
    error_code: str
    reason: str | None = None
    path: str | None = None
    audit_id: str | None = None
    # A refused message of the RCAN 3.x generation: its id, and `outcome` as its status.
    msg_id: str | None = None
    status: Status3 | None = None


class PendingAuth(msgspec.Struct, kw_only=True):
    """PENDING_AUTH: what the HiTL webhook receives and GET /api/hitl/pending lists."""

    pending_id: str
    original_command: dict[str, Any]
    confidence: float | None
    ai_model: str | None
    requires_auth_from_role: RoleName
    expires_at_ms: int
    issued_by: str
    message_type: Literal["PENDING_AUTH"] = "PENDING_AUTH"
    # n-of-m approval (`hitl.gates[].approvals`): how many distinct approvers it needs, and
    # the approvals it has so far.
    approvals_required: int = 1
    approvals: list[Approval] = []
    # When its issuer's credential ends (a JWT's `exp` plus the leeway, a client
    # certificate's notAfter), if before `expires_at_ms`: the hold is withdrawn then, and an
    # approval after it is refused `issuer_credential_expired`. None: it ends no sooner.
    issuer_credential_ends_at_ms: int | None = None


class Authorize(Strict, frozen=True):
    """Body of POST /api/hitl/authorize, /api/hitl/deny and /api/hitl/withdraw; `reason` is
    recorded in the audit."""

    pending_id: Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
    reason: ShortText | None = None


class Position(msgspec.Struct):
    x: float
    y: float
    z: float


class Velocity(msgspec.Struct):
    linear_x: float
    angular_z: float


class Joints(msgspec.Struct):
    """The robot's JointState: at most 64 joints are listed (the commanded arms' first)."""

    names: list[str]
    positions: list[float]
    velocities: list[float]
    count: int | None = None  # joints the JointState had (more than listed when it was cut)


class Fault(msgspec.Struct):
    name: str
    message: str
    level: Literal["WARN", "ERROR", "STALE"]


class ForeignPublisher(msgspec.Struct, kw_only=True):
    """Another participant publishing on a topic the bridge commands the robot on: the robot
    obeys it too, between the bridge's samples, and an e-stop cannot hold against it."""

    topic: str
    type: str
    participant: str  # its participant's GUID prefix (12 bytes, hex, dotted)
    node: str | None = None  # the node's fully qualified name, if its participant names it
    writers: int = 1  # its writers on this topic
    # Declared in `bridge.ros2.foreign_publishers.expected` for this topic: every one of its
    # writers here belongs to a named node listed there (an unnamed one never does).
    expected: bool = False


class Telemetry(msgspec.Struct):
    position: Position | None = None
    yaw: float | None = None
    velocity: Velocity | None = None
    joints: Joints | None = None


class RosInfo(msgspec.Struct):
    domain_id: int
    distro: str
    connected: bool
    last_telemetry_age_s: float | None


class Navigation(msgspec.Struct, kw_only=True):
    """The navigation goal in progress, from its latest NavigateToPose feedback."""

    goal_id: str
    state: str
    distance_remaining: float | None = None  # metres
    eta_s: float | None = None  # the planner's estimate of the time left
    recoveries: int | None = None  # recovery behaviours run so far
    navigation_time_s: float | None = None


class RobotPosition(msgspec.Struct):
    """§20.3's `position`: world-frame x, y (m) and heading (rad)."""

    x: float
    y: float
    heading_rad: float | None


class Capability(msgspec.Struct, kw_only=True):
    """A Capability Descriptor of RCAN §18.2."""

    version: str = "1.0"
    required: bool = False
    params: dict[str, Any] = msgspec.field(default_factory=dict)


def invoke_caps(skills: Iterable[str]) -> dict[str, Capability]:
    """§18's Capability Object Map of what an INVOKE may name: the `invoke` capability,
    its `params.skills` every skill declared (§19.7: an INVOKE's skill MUST be one of
    them). Listed with no skill too: INVOKE is always answered (7001 for a skill not
    declared), so a client learns from the empty list rather than from a missing key."""
    return {"invoke": Capability(params={"skills": sorted(skills)})}


class Status(msgspec.Struct, kw_only=True):
    """STATUS (GET /api/status and the WebSocket stream).

    The §20 Telemetry Field Registry's names (the Robot State object, and the conformance
    suite's `battery_percent`/`cpu_percent`) come beside the profile's own fields; §20.2's
    per-joint objects are left out: a JointState does not say which joints are prismatic
    (`position_m`) and which revolute (`position_rad`)."""

    ruri: str
    state: Literal["idle", "moving", "executing", "estop", "fault", "safe_stop", "offline"]
    estop: bool
    battery_pct: float | None
    telemetry: Telemetry
    faults: list[Fault]
    active_goals: list[str]
    pending_auth: int
    ros: RosInfo
    timestamp_ms: int
    navigation: Navigation | None = None  # the newest active goal, while there is one
    # RCAN §20 (see above), None where not known:
    battery_percent: float | None = None  # = battery_pct, 0-100
    battery_v: float | None = None  # BatteryState.voltage
    cpu_percent: float | None = None  # 0-100, of the machine the bridge runs on
    uptime_ms: int | None = None  # since the bridge started
    seq: int | None = None  # grows with every STATUS computed
    timestamp_us: int | None = None  # µs since the epoch, increasing within a run
    position: RobotPosition | None = None  # from odometry
    # Other participants publishing on the topics the bridge commands the robot on (at most
    # 32 listed; `foreign_publishers_count` says how many there are).
    foreign_publishers: list[ForeignPublisher] = []
    foreign_publishers_count: int = 0
    # §18.4: the robot's capabilities as a Capability Object Map: the `invoke` capability
    # (invoke_caps), as GET /api/skills gives it.
    caps: dict[str, Capability] = {}
