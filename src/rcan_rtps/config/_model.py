"""Typed `.rcan.yaml`: the bridge spec's §5 keys plus the profile's additions.

A check of one field's value beyond its type (a ROS name, a polygon) is attached to the field's
type with `_check`, so the loader reports it at that key's path and line; a check that spans
fields lives in `__post_init__` and is reported at the section's path.
"""

from __future__ import annotations

import functools
import ipaddress
import math
import os
import re
from collections.abc import Callable, Iterable
from typing import Annotated, Any, Literal

import msgspec
import msgspec.inspect

from rcan_rtps.rcan import (
    ActionName,
    AnyRoleName,
    Effect,
    GateableName,
    InvalidRuriError,
    Role,
    parse_ruri,
    whole,
)
from rcan_rtps.rcan.actions import GoalRoute, goal_routes, specs, with_effect

from ._skills import skill_problem

# A relative, absolute or `~/` name of one or more tokens. rcl wants `~` followed by `/` (or
# alone): `~cmd_vel` would resolve to `/ns/rcan_bridgecmd_vel`, the node's name run into it.
_ROS_NAME = re.compile(r"^(~/|/)?([A-Za-z_][A-Za-z0-9_]*)(/[A-Za-z_][A-Za-z0-9_]*)*$")
# whole(): a bare `$` also matched before a final newline ("admin\n" loaded beside admin).
_NODE_NAME = whole(r"[A-Za-z_][A-Za-z0-9_]*")
_PRINCIPAL = whole(r"[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}")
_ENV_NAME = whole(r"[A-Za-z_][A-Za-z0-9_]*")

# What is wrong with a field's (already well-typed) value, or None.
Problem = Callable[[Any], str | None]
_CHECK = "rcan_check"


def _check(problem: Problem) -> msgspec.Meta:
    return msgspec.Meta(extra={_CHECK: problem})


def field_check(info: msgspec.inspect.Type) -> Problem | None:
    """The `_check` attached to a field's type, if any."""
    if isinstance(info, msgspec.inspect.Metadata) and info.extra:
        problem: Problem | None = info.extra.get(_CHECK)
        return problem
    return None


def _optional_check(info: msgspec.inspect.Type) -> Problem | None:
    """The check of `X | None`'s X, passing None: the loader's walk checks the value of an
    optional field, so direct construction (and msgspec.convert) must too."""
    if not isinstance(info, msgspec.inspect.UnionType):
        return field_check(info)
    checks = [field_check(t) for t in info.types if not isinstance(t, msgspec.inspect.NoneType)]
    if len(checks) != 1 or checks[0] is None:
        return None
    inner = checks[0]
    return lambda value: None if value is None else inner(value)


@functools.cache
def _field_checks(cls: type[msgspec.Struct]) -> tuple[tuple[str, Problem], ...]:
    info = msgspec.inspect.type_info(cls)
    assert isinstance(info, msgspec.inspect.StructType)
    checks = ((field.name, _optional_check(field.type)) for field in info.fields)
    return tuple((name, problem) for name, problem in checks if problem is not None)


def _ros_name_problem(value: str) -> str | None:
    if _ROS_NAME.fullmatch(value):
        return None
    if value.startswith("~") and not value.startswith("~/"):
        # rcl lets a two-character `~x` through (its check starts at three): refused all
        # the same, it is the same mistake.
        return (f"is not a valid ROS name: {value!r}: '~' must be followed by '/' "
                f"(write {'~/' + value[1:]!r} for a topic inside the bridge's node)")
    return f"is not a valid ROS name: {value!r}"


def _namespace_problem(value: str) -> str | None:
    if value.startswith("~"):
        return f"is not a valid namespace: {value!r}: a namespace has no '~'"
    return None if value in ("", "/") else _ros_name_problem(value)


def _ruri_problem(value: str) -> str | None:
    try:
        parse_ruri(value)
    except InvalidRuriError as exc:
        return exc.rule
    return None


Positive = Annotated[float, msgspec.Meta(gt=0.0, le=1e6)]
RosName = Annotated[str, msgspec.Meta(min_length=1, max_length=256)]
RosTopic = Annotated[RosName, _check(_ros_name_problem)]
EnvName = Annotated[str, msgspec.Meta(pattern=_ENV_NAME)]
Point = tuple[float, float]
Seconds = Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)]


class _Section(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    def __post_init__(self) -> None:
        # The loader has run these already; this keeps msgspec (and direct construction) honest.
        for name, problem_of in _field_checks(type(self)):
            problem = problem_of(getattr(self, name))
            if problem is not None:
                raise ValueError(f"`{name}`: {problem}")


class RobotConfig(_Section, frozen=True, kw_only=True):
    ruri: Annotated[str, _check(_ruri_problem)]
    name: str = ""
    # Who operates the robot, as the node manifest names it (default: the RURI's manufacturer).
    operator: Annotated[str, msgspec.Meta(max_length=256)] = ""


ArmName = Annotated[str, msgspec.Meta(pattern=whole(r"[a-z][a-z0-9_]{0,63}"))]
JointName = Annotated[str, msgspec.Meta(min_length=1, max_length=128,
                                        pattern=whole(r"[A-Za-z0-9_./-]+"))]


def _repeated_joint_problem(joints: list[str]) -> str | None:
    return "lists a joint more than once" if len(set(joints)) != len(joints) else None


ImageName = Annotated[str, msgspec.Meta(pattern=whole(r"[a-z][a-z0-9_]{0,63}"))]


class ImageFeedConfig(_Section, frozen=True, kw_only=True):
    """A camera topic clients may look at (GET /api/images/{name}, MCP `robot://image/...`):
    raw frames are shown as PNG, compressed ones as they come (JPEG or PNG)."""

    topic: RosTopic
    type: Literal["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"] = (
        "sensor_msgs/msg/Image")


class ArmConfig(_Section, frozen=True, kw_only=True):
    """One arm: its trajectory controller's topic and the joints it owns (empty: any)."""

    topic: RosTopic
    joints: Annotated[list[JointName], _check(_repeated_joint_problem)] = []


_NODE_FQN = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")


def _expected_problem(expected: dict[str, list[str]]) -> str | None:
    """Each topic's expected publishers: fully qualified node names, each once."""
    for topic, nodes in expected.items():
        for node in nodes:
            if not _NODE_FQN.fullmatch(node):
                return (f"{topic}: {node!r} is not a fully qualified node name (as `ros2 node "
                        f"list` prints it, e.g. /controller_server or /robot1/velocity_smoother)")
        if len(set(nodes)) != len(nodes):
            return f"{topic}: lists a node more than once"
    return None


class ForeignPublishersConfig(_Section, frozen=True, kw_only=True):
    """Other publishers on the topics the bridge commands the robot on (bridge/commanders.py).

    `expected`: command topic (resolved like the other topics) → the fully qualified names of
    the nodes meant to publish there too (nav2's controller_server, velocity_smoother,
    collision_monitor, a twist_mux). They are still listed, logged and audited, marked
    expected, but raise no WARN fault; while the e-stop is latched one on a motion topic is
    still reported as a fault (docs/governance.md says which level, and why). A publisher
    whose node cannot be learned (no ros_discovery_info) is never expected."""

    poll_s: Annotated[float, msgspec.Meta(ge=0.1, le=10.0)] = 1.0  # how often the graph is read
    expected: Annotated[
        dict[RosTopic, Annotated[list[Annotated[str, msgspec.Meta(max_length=256)]],
                                 msgspec.Meta(min_length=1, max_length=64)]],
        _check(_expected_problem)] = {}


class Ros2Config(_Section, frozen=True, kw_only=True):
    namespace: Annotated[str, _check(_namespace_problem)] = ""
    node_name: Annotated[str, msgspec.Meta(pattern=_NODE_NAME)] = "rcan_bridge"
    domain_id: Annotated[int, msgspec.Meta(ge=0, le=232)] = 0
    distro: Literal["humble", "jazzy", "kilted"] = "jazzy"
    cmd_vel_topic: RosTopic = "cmd_vel"
    cmd_vel_type: Literal["geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped"] = (
        "geometry_msgs/msg/Twist"
    )
    estop_topic: RosTopic = "emergency_stop"
    joint_states_topic: RosTopic = "joint_states"
    joint_trajectory_topic: RosTopic = "joint_trajectory_controller/joint_trajectory"
    # Several arms: `arm_joint` names one by `group`; then joint_trajectory_topic is unused.
    arms: dict[ArmName, ArmConfig] = {}
    # Goal action servers; null: the robot has none (its goals are refused, and the bridge
    # makes no action client for it, nor loads the modules of one: idle memory, issue 27).
    nav_action: RosTopic | None = "navigate_to_pose"  # nav2 NavigateToPose (`navigate`)
    dock_action: RosTopic | None = "dock_robot"  # nav2 DockRobot, opennav_docking's (`dock`)
    odom_topic: RosTopic = "odom"
    diagnostics_topic: RosTopic = "diagnostics"
    battery_topic: RosTopic = "battery_state"
    images: dict[ImageName, ImageFeedConfig] = {}  # none: no camera is shown
    telemetry_rate_hz: Annotated[float, msgspec.Meta(gt=0.0, le=100.0)] = 10.0
    nav_frame_id: Annotated[str, msgspec.Meta(min_length=1, max_length=128)] = "map"
    # Telemetry older than this makes the robot `offline`.
    telemetry_stale_s: Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)] = 2.0
    # How long a command waits for a subscriber or action server before ROBOT_UNAVAILABLE.
    match_timeout_s: Annotated[float, msgspec.Meta(gt=0.0, le=60.0)] = 1.0
    # How long a start's take-back of what a crashed run left waits for each peer (an arm's
    # trajectory topic and its joint_states, a goal's server), at least match_timeout_s:
    # the API is not serving yet, and an arm not heard by then is reported, not held (a
    # busy board's joint_states can take more than a second to be heard after joining).
    crash_halt_wait_s: Annotated[float, msgspec.Meta(gt=0.0, le=60.0)] = 5.0
    # How often a streamed `move` republishes its velocity (ros2_control's diff drive stops
    # after 0.5 s without a command: 20 Hz leaves ten samples of margin).
    cmd_rate_hz: Annotated[float, msgspec.Meta(ge=1.0, le=1000.0)] = 20.0
    # Request-reply mapping of services/actions: `auto` picks it from the server's DDS vendor
    # (Cyclone's in-band header, or Fast DDS's plain requests); per-name overrides win.
    request_mapping: Literal["auto", "cyclone", "fastdds"] = "auto"
    request_mappings: dict[RosName, Literal["auto", "cyclone", "fastdds"]] = {}
    foreign_publishers: ForeignPublishersConfig = ForeignPublishersConfig()
    # The largest sample (CDR bytes) the bridge takes from the graph or sends: any peer may
    # write one of any size to a topic it reads, reassembled whole before anything can look
    # at it. Larger ones are dropped as they arrive. The default (256 MiB) is above what ROS
    # sends (a 4K Image is 25 MB); a robot may set less. CYCLONEDDS_URI's MaxSampleSize wins.
    max_sample_bytes: Annotated[int, msgspec.Meta(ge=65536, lt=1 << 31)] = 256 << 20

    def __post_init__(self) -> None:
        super().__post_init__()
        problem = goal_routes_problem(self, goal_routes()) or expected_topics_problem(self)
        if problem is not None:
            raise ValueError(problem)

    def command_topics(self) -> set[str]:
        """Every topic the registry's actions publish to, resolved (as RosDispatcher binds
        them: a grouped route on each group's topic, else on its key's)."""
        topics: set[str] = set()
        for spec in specs():
            for publish in spec.ros.publishes():
                groups = getattr(self, publish.group_key) if publish.group_key else {}
                names = ([g.topic for g in groups.values()] if groups
                         else [getattr(self, publish.topic_key)])
                topics.update(self.resolve(name) for name in names)
        return topics

    def expected_publishers(self) -> dict[str, frozenset[str]]:
        """`foreign_publishers.expected` by resolved topic."""
        expected = self.foreign_publishers.expected
        return {self.resolve(topic): frozenset(nodes) for topic, nodes in expected.items()}

    def resolve(self, name: str) -> str:
        """The fully qualified name of a configured topic or action, as the node resolves it:
        absolute as is, `~` inside the node, anything else inside `namespace`."""
        namespace = self.namespace.rstrip("/")
        if name.startswith("/"):
            return name
        if name.startswith("~"):
            return f"{namespace}/{self.node_name}{name[1:]}"
        return f"{namespace}/{name}"


def expected_topics_problem(ros2: Ros2Config) -> str | None:
    """An expected publisher declared on a topic the bridge does not command the robot on
    would never be looked at: a typo, said at once."""
    commanded = ros2.command_topics()
    resolved: dict[str, str] = {}
    for topic in ros2.foreign_publishers.expected:
        full = ros2.resolve(topic)
        if full not in commanded:
            return (f"`foreign_publishers.expected` names {topic!r} ({full}), which is not a "
                    f"topic the bridge commands the robot on: {', '.join(sorted(commanded))}")
        other = resolved.setdefault(full, topic)
        if other != topic:
            return (f"`foreign_publishers.expected` names {full} twice ({other!r} and "
                    f"{topic!r}): list its nodes once")
    return None


def goal_routes_problem(ros2: Ros2Config, routes: tuple[GoalRoute, ...]) -> str | None:
    """Why the registry's goal routes cannot each reach a server of their own type, or None:
    a route whose key `bridge.ros2` does not have, or two keys naming one action server for
    two action types (a goal would go to a server that cannot take it)."""
    servers: dict[str, GoalRoute] = {}
    for route in routes:
        name = getattr(ros2, route.action_key, None)
        if route.action_key not in Ros2Config.__struct_fields__ or not (
                name is None or isinstance(name, str)):
            return (f"action {', '.join(route.actions)} sends {route.type_name} goals to the "
                    f"server named by `{route.action_key}`, which bridge.ros2 does not have")
        if name is None:
            continue  # no such server: its goals are refused
        resolved = ros2.resolve(name)
        seen = servers.setdefault(resolved, route)
        if seen.type_name != route.type_name:
            return (f"`{seen.action_key}` and `{route.action_key}` both name the action "
                    f"server {resolved}, for {seen.type_name} ({', '.join(seen.actions)}) and "
                    f"{route.type_name} ({', '.join(route.actions)}): give each its own name")
    return None


class ConfidenceGate(_Section, frozen=True, kw_only=True):
    min_confidence: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
    on_fail: Literal["block", "escalate"] = "block"


class HitlGate(_Section, frozen=True, kw_only=True):
    action: GateableName  # never an action that stops the robot
    require_auth: bool = True
    authorized_roles: list[AnyRoleName] = []
    # Distinct approvers a held command of this action needs (n-of-m); above 1 its issuer
    # never counts as one of them.
    approvals: Annotated[int, msgspec.Meta(ge=1, le=16)] = 1


def _repeated_gate_problem(gates: list[HitlGate]) -> str | None:
    actions = [g.action for g in gates]
    return "lists an action more than once" if len(set(actions)) != len(actions) else None


AUTHORIZE_PATH = "/api/hitl/authorize"


def _authorize_endpoint_problem(path: str) -> str | None:
    if path == AUTHORIZE_PATH:
        return None
    return f"approvals are served at {AUTHORIZE_PATH} only (a proxy may map another path)"


class HitlConfig(_Section, frozen=True, kw_only=True):
    notify_webhook: Annotated[str, msgspec.Meta(pattern=whole(r"https?://\S+"))] | None = None
    timeout_seconds: Annotated[float, msgspec.Meta(gt=0.0, le=86400.0)] = 300.0
    confidence_gate: ConfidenceGate | None = None
    gates: Annotated[list[HitlGate], _check(_repeated_gate_problem)] = []
    require_distinct_approver: bool = False
    # The bridge spec's key, kept so its configs load: approvals are served at this one path.
    authorize_endpoint: Annotated[str, _check(_authorize_endpoint_problem)] = AUTHORIZE_PATH


KeyId = Annotated[str, msgspec.Meta(min_length=1, max_length=128,
                                    pattern=whole(r"[A-Za-z0-9._:-]+"))]
# off: a `sig` is recorded, not checked; verify: a `sig` must verify with one of the
# principal's keys, unsigned messages pass; required: every command but a stop must be signed.
SignaturePolicy = Literal["off", "verify", "required"]


class SignerKey(_Section, frozen=True, kw_only=True):
    """A public key its principal signs RCAN 3.x COMMANDs with (docs/rcan-profile.md): the
    `kid` the signatures name (the SDK's is `MLDSAKeyPair.key_id`), and the key, inline
    (base64 of its raw bytes) or in a file (raw bytes, as `MLDSAKeyPair.save_public` writes
    them, or PEM)."""

    kid: KeyId
    alg: Literal["ml-dsa-65", "ed25519"] = "ml-dsa-65"
    public_key: Annotated[str, msgspec.Meta(min_length=1, max_length=8192)] | None = None
    public_key_file: Annotated[str, msgspec.Meta(min_length=1)] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.public_key is None) == (self.public_key_file is None):
            raise ValueError("give exactly one of `public_key` or `public_key_file`")


def _repeated_kid_problem(keys: list[SignerKey]) -> str | None:
    kids = [key.kid for key in keys]
    return "lists a kid more than once" if len(set(kids)) != len(kids) else None


class SignaturesConfig(_Section, frozen=True, kw_only=True):
    policy: SignaturePolicy = "verify"
    keys: Annotated[list[SignerKey], _check(_repeated_kid_problem)] = []


class PrincipalConfig(_Section, frozen=True, kw_only=True):
    name: Annotated[str, msgspec.Meta(pattern=_PRINCIPAL)]
    role: AnyRoleName  # the profile's names or RCAN v2's (OPERATOR = USER, …; see Role)
    token_env: EnvName | None = None
    token_sha256: Annotated[str, msgspec.Meta(pattern=whole(r"[0-9a-fA-F]{64}"))] | None = None
    rate_limit_per_min: Annotated[int, msgspec.Meta(ge=1)] | None = None
    # Signed messages; absent: policy off (a `sig` is recorded, not checked).
    signatures: SignaturesConfig | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.token_env is None) == (self.token_sha256 is None):
            raise ValueError("give exactly one of `token_env` or `token_sha256`")


class TlsConfig(_Section, frozen=True, kw_only=True):
    cert: str
    key: str
    client_ca: str | None = None


class JwtConfig(_Section, frozen=True, kw_only=True):
    """EdDSA JWTs. A JWT's principal is `jwt:<iss>/<sub>`, never a configured principal."""

    # Exactly one: a PEM file of the issuer's Ed25519 public key (a token's `kid` is not
    # looked at), or a JWKS file (RFC 7517) whose keys tokens choose by `kid` (rotation).
    public_key: str | None = None
    jwks: str | None = None
    audience: Annotated[str, msgspec.Meta(min_length=1)]
    issuer: Annotated[str, msgspec.Meta(min_length=1)] | None = None
    leeway_s: Annotated[float, msgspec.Meta(ge=0.0, le=300.0)] = 30.0
    # exp - iat (or exp - now, without iat) above this is refused: no token lasts for ever.
    max_lifetime_s: Annotated[float, msgspec.Meta(gt=0.0, le=366 * 86400.0)] = 86400.0
    # The role of a token whose role is RCAN v2's M2M_TRUSTED (`rcan_role` 6, RRF-issued fleet
    # orchestration); unset, such tokens are refused.
    m2m_trusted_role: AnyRoleName | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.public_key is None) == (self.jwks is None):
            raise ValueError("give exactly one of `public_key` or `jwks`")


def _principals_problem(principals: list[PrincipalConfig]) -> str | None:
    names = [p.name for p in principals]
    if len(set(names)) != len(names):
        return "repeats a name"
    folded: dict[str, str] = {}
    for name in names:
        other = folded.setdefault(name.casefold(), name)
        if other != name:
            # Two principals a reader of the audit log, or a certificate's CN, tells apart by
            # case alone: one name, two roles.
            return f"{other!r} and {name!r} differ only in case"
    digests = [p.token_sha256.lower() for p in principals if p.token_sha256]
    if len(set(digests)) != len(digests):
        return "two share a token_sha256"
    owners: dict[str, str] = {}
    for p in principals:
        for key in p.signatures.keys if p.signatures else []:
            other = owners.setdefault(key.kid, p.name)
            if other != p.name:
                return f"kid {key.kid!r} is bound to two principals ({other}, {p.name})"
    return None


class ApiConfig(_Section, frozen=True, kw_only=True):
    host: str = "127.0.0.1"  # loopback unless the deployment opts in to a network
    port: Annotated[int, msgspec.Meta(ge=1, le=65535)] = 8765
    auth_token_env: EnvName | None = None
    principals: Annotated[list[PrincipalConfig], _check(_principals_problem)] = []
    tls: TlsConfig | None = None
    jwt: JwtConfig | None = None
    max_body_bytes: Annotated[int, msgspec.Meta(ge=256, le=16 * 1024 * 1024)] = 64 * 1024
    # Slow or silent peers: request headers complete within header_timeout_s of connecting
    # (or of the previous request's end + keepalive_timeout_s, which is also the idle limit of
    # a kept-alive connection); a body complete within body_timeout_s of its headers (408).
    header_timeout_s: Seconds = 10.0
    body_timeout_s: Seconds = 30.0
    keepalive_timeout_s: Seconds = 30.0
    # Serve plain HTTP on a non-loopback `host` (bearer tokens in clear on the network): only
    # behind something that encrypts (a TLS-terminating proxy, a VPN) that the bridge cannot see.
    allow_plaintext: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (self.principals or self.auth_token_env or self.jwt):
            raise ValueError("no way to authenticate: set principals, auth_token_env or jwt")
        problem = plaintext_problem(self, self.host)
        if problem is not None:
            raise ValueError(problem)


def is_loopback(host: str) -> bool:
    """Whether `host` is a loopback address or `localhost` (a name that could resolve
    elsewhere, and the empty host or 0.0.0.0 meaning every interface, are not)."""
    if host.lower().rstrip(".") == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def plaintext_problem(api: ApiConfig, host: str) -> str | None:
    """Why serving `api` on `host` would put credentials on the network in clear, or None."""
    if api.tls is not None or api.allow_plaintext or is_loopback(host):
        return None
    return (f"`host` {host!r} is not loopback and there is no `tls`: bearer tokens would cross "
            "the network in clear. Set `tls` (cert, key; client_ca for mTLS), or "
            "`allow_plaintext: true` if something outside the bridge encrypts the traffic")


def _workspace_problem(workspace: list[Point] | None) -> str | None:
    return None if workspace is None else polygon_problem(workspace)


class SafetyConfig(_Section, frozen=True, kw_only=True):
    # No default limits: a safe speed depends on the robot, so the deployment must say it.
    max_linear_vel: Positive
    max_angular_vel: Positive
    velocity_exceed_deny: bool = True
    session_timeout_s: Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)] = 2.0
    workspace: Annotated[list[Point] | None, _check(_workspace_problem)] = None
    estop_state_path: str | None = None  # default: estop.state beside the audit log
    # A timed move lasts at most this; longer requests are denied (a held move has no end but
    # its sender's session, which needs heartbeats).
    max_move_duration_s: Annotated[float, msgspec.Meta(gt=0.0, le=86400.0)] = 30.0
    # A timed move is held too: it ends (session_lost) once its sender has been silent this
    # long (no command, heartbeat or WebSocket frame); None: `session_timeout_s`.
    unattended_move_s: Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)] | None = None
    # Velocity streams ramp within these (m/s², rad/s²); None: no ramp (the robot's own
    # controller limits acceleration). Stopping is never ramped: a stop is zero at once.
    max_linear_accel: Positive | None = None
    max_angular_accel: Positive | None = None


def _witness_problem(url: str | None) -> str | None:
    if url is None:
        return None
    from rcan_rtps.governance.witness import witness_problem  # the witness's own rule

    return witness_problem(url)


# The files an audit log keeps beside itself (`<log><suffix>`): governance/audit.py,
# resume.py and treehead.py name them; a test keeps this list equal to theirs.
AUDIT_SIDECARS = (".checkpoint", ".resume", ".sth", ".pub")


def estop_state_file(bridge: BridgeConfig) -> str:
    """Where the e-stop latch is kept: `safety.estop_state_path`, else estop.state beside the
    audit log."""
    default = os.path.join(os.path.dirname(bridge.audit.path), "estop.state")
    return bridge.safety.estop_state_path or default


class AuditConfig(_Section, frozen=True, kw_only=True):
    path: str = "/var/lib/rcan/audit.jsonl"
    key_path: str = "/var/lib/rcan/audit-ed25519.key"
    # Where each signed tree head is sent (file:///abs/path appended, http(s):// POSTed).
    witness: Annotated[str | None, _check(_witness_problem)] = None


def _action_roles_problem(action_roles: dict[ActionName, AnyRoleName]) -> str | None:
    # An e-stop must always be available to any authenticated principal.
    estop = with_effect(Effect.ESTOP).name
    if Role[action_roles.get(estop, "GUEST")] is not Role.GUEST:
        return f"{estop} cannot be raised above GUEST"
    return _lowered_role_problem(action_roles)


def _lowered_role_problem(action_roles: dict[ActionName, AnyRoleName]) -> str | None:
    """A role below the action's default (docs/actions.md: roles may be raised): a table
    that let a GUEST clear anyone's e-stop, or drive, loaded without a word."""
    defaults = {spec.name: spec.default_role for spec in specs()}
    for action, name in action_roles.items():
        default = defaults.get(action)
        if default is not None and Role[name] < default:
            return (f"{action}: {name} is below its default role {default.name}; a role "
                    "may be raised, never lowered")
    return None


def _same_role_twice_problem(by_role: dict[AnyRoleName, Any]) -> str | None:
    """Keys that are two names of one role (USER and OPERATOR): which would count?"""
    seen: dict[Role, str] = {}
    for name in by_role:
        other = seen.setdefault(Role[name], name)
        if other != name:
            return f"{other} and {name} name the same role ({Role[name].name})"
    return None


class RbacConfig(_Section, frozen=True, kw_only=True):
    action_roles: Annotated[dict[ActionName, AnyRoleName], _check(_action_roles_problem)] = {}
    rate_limits_per_min: Annotated[
        dict[AnyRoleName, Annotated[int, msgspec.Meta(ge=1)] | None],
        _check(_same_role_twice_problem)] = {}
    hitl_approver_role: AnyRoleName = "OWNER"
    audit_read_role: AnyRoleName = "LEASEE"


Priority = Annotated[int, msgspec.Meta(ge=0, le=1_000_000)]


class MotionLock(_Section, frozen=True, kw_only=True):
    name: Annotated[str, msgspec.Meta(min_length=1, max_length=64,
                                      pattern=whole(r"[A-Za-z0-9_.-]+"))]
    priority: Priority


def _repeated_lock_problem(locks: list[MotionLock]) -> str | None:
    names = [lock.name for lock in locks]
    return "names a lock more than once" if len(set(names)) != len(names) else None


class MotionConfig(_Section, frozen=True, kw_only=True):
    """Who may take over a velocity stream (twist_mux-like): a higher priority preempts a
    lower one, a lower one is refused; a principal's own priority wins over its role's."""

    default_priority: Priority = 0
    role_priorities: Annotated[dict[AnyRoleName, Priority],
                               _check(_same_role_twice_problem)] = {}
    principal_priorities: dict[Annotated[str, msgspec.Meta(min_length=1, max_length=128)],
                               Priority] = {}
    locks: Annotated[list[MotionLock], _check(_repeated_lock_problem)] = []


class SecurityConfig(_Section, frozen=True, kw_only=True):
    """RCAN §8.3 for messages carrying rcan_version >= 1.5 (the spec's `security` keys)."""

    replay_window_s: Annotated[float, msgspec.Meta(ge=5.0, le=300.0)] = 30.0
    msg_id_cache_size: Annotated[int, msgspec.Meta(ge=100, le=1_000_000)] = 10_000
    # A sender's clock may run this far ahead of the bridge's (§8.4's drift tolerance).
    clock_ahead_s: Annotated[float, msgspec.Meta(ge=0.0, le=60.0)] = 5.0


ParamName = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
SkillName = Annotated[str, msgspec.Meta(
    min_length=1, max_length=128, pattern=whole(r"[a-z][a-z0-9_]*(\.[a-z][a-z0-9_]*)*"))]


class SkillConfig(_Section, frozen=True, kw_only=True):
    """One skill an INVOKE may name (RCAN §19): a registry action (never a stop: those have
    their own lane), its fixed parameters, and those the invoker may set."""

    action: GateableName
    params: dict[ParamName, Any] = {}
    allow: list[ParamName] = []
    description: Annotated[str, msgspec.Meta(max_length=256)] = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        problem = skill_problem(self.action, self.params, self.allow)
        if problem is not None:
            raise ValueError(problem)


ModelName = Annotated[str, msgspec.Meta(min_length=1, max_length=256)]


def _models_problem(agents: dict[str, list[str]]) -> str | None:
    for name, models in agents.items():
        if not models:
            return f"{name!r} is bound to no model (leave it out to bind it to none)"
        if len(set(models)) != len(models):
            return f"{name!r} lists a model more than once"
    return None


class AiConfig(_Section, frozen=True, kw_only=True):
    """AI accountability (§16.1). An AI command (one carrying `confidence`, `ai` or `ai_*`) must
    name its model, always; `agents` binds principals to the models they may name: each of
    their commands must then be an AI command naming one of them. Keys are principals' names
    (`api.principals[].name`, or a JWT's `jwt:<iss>/<sub>`)."""

    agents: Annotated[dict[Annotated[str, msgspec.Meta(min_length=1, max_length=256)],
                           list[ModelName]], _check(_models_problem)] = {}


def unknown_agents_problem(ai: AiConfig, api: ApiConfig) -> str | None:
    """Agents that name no principal this config can authenticate (a typo would bind no one)."""
    return unknown_principals_problem("ai.agents", ai.agents, api)


def unknown_principals_problem(key: str, names: Iterable[str], api: ApiConfig) -> str | None:
    """The first of `names` (keys of `key`) that is no principal this config can
    authenticate: a typo, or a look-alike (`аdmin` with a Cyrillic а), would bind no one."""
    known = {p.name for p in api.principals}
    if not api.principals and api.auth_token_env:
        known.add("default")  # auth_token_env's one principal
    for name in names:
        if name.startswith("jwt:"):
            if api.jwt is None:
                return f"`{key}` names {name!r}, but there is no `api.jwt`"
        elif name not in known:
            return (f"`{key}` names {name!r}, which is not in `api.principals` "
                    "(a JWT's principal is `jwt:<iss>/<sub>`)")
    return None


def issuer_roles(rbac: RbacConfig) -> dict[str, Role]:
    """The role each action needs to be issued: its default, as `rbac.action_roles` raises it
    (governance.RolePolicy's table; the e-stop is never gated, so its GUEST is not needed)."""
    return {spec.name: Role[rbac.action_roles.get(spec.name, spec.default_role.name)]
            for spec in specs()}


def approver_below_issuer_problem(hitl: HitlConfig, rbac: RbacConfig) -> str | None:
    """An approver role below the role its held action needs to be issued: a viewer (GUEST)
    approving an AI's move releases motion it may not command itself. A gate's
    `authorized_roles` are judged against its action's role; `rbac.hitl_approver_role`
    against the lowest role of any action a human may be asked about (an action the
    confidence gate holds whose role is higher is approved at that role: governance.hitl)."""
    needs = issuer_roles(rbac)
    for index, gate in enumerate(hitl.gates):
        for name in gate.authorized_roles:
            if Role[name] < needs[gate.action]:
                return (f"`hitl.gates[{index}].authorized_roles` lets {name} approve "
                        f"{gate.action}, which needs {needs[gate.action].name} to be issued: "
                        "an approver must be allowed to issue what it approves")
    lowest = min(needs[spec.name] for spec in specs() if spec.hitl.gateable)
    if Role[rbac.hitl_approver_role] < lowest:
        return (f"`rbac.hitl_approver_role` is {rbac.hitl_approver_role}, below {lowest.name}, "
                "the lowest role that may issue anything a human is asked to approve: an "
                "approver must be allowed to issue what it approves")
    return None


class BridgeConfig(_Section, frozen=True, kw_only=True):
    type: Literal["ros2"] = "ros2"
    ros2: Ros2Config = Ros2Config()
    hitl: HitlConfig = HitlConfig()
    api: ApiConfig
    safety: SafetyConfig
    audit: AuditConfig = AuditConfig()
    rbac: RbacConfig = RbacConfig()
    motion: MotionConfig = MotionConfig()
    security: SecurityConfig = SecurityConfig()
    skills: dict[SkillName, SkillConfig] = {}  # what INVOKE may run (§19)
    ai: AiConfig = AiConfig()

    def __post_init__(self) -> None:
        super().__post_init__()
        problem = (unknown_agents_problem(self.ai, self.api) or unknown_principals_problem(
            "motion.principal_priorities", self.motion.principal_priorities, self.api)
            or approver_below_issuer_problem(self.hitl, self.rbac))
        if problem is not None:
            raise ValueError(problem)


class RcanConfig(_Section, frozen=True, kw_only=True):
    robot: RobotConfig
    bridge: BridgeConfig


def polygon_problem(points: list[Point]) -> str | None:
    """Why a polygon cannot bound a workspace, or None if it can."""
    if len(points) < 3:
        return "needs at least 3 points"
    if not all(math.isfinite(c) for p in points for c in p):
        return "has a non-finite coordinate"
    if _self_intersects(points):
        return "crosses itself"
    if abs(_area2(points)) < 1e-9:
        return "has zero area"
    return None


def polygon_edges(pts: list[Point]) -> list[tuple[Point, Point]]:
    """Each edge of the closed polygon, last point back to the first."""
    return list(zip(pts, pts[1:] + pts[:1], strict=True))


def _area2(pts: list[Point]) -> float:
    return sum(a[0] * b[1] - b[0] * a[1] for a, b in polygon_edges(pts))


def _cross(o: Point, a: Point, b: Point) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(p1: Point, p2: Point, q1: Point, q2: Point) -> bool:
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    return d1 * d2 < 0 and d3 * d4 < 0


def _self_intersects(pts: list[Point]) -> bool:
    edges = polygon_edges(pts)
    n = len(edges)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # neighbours share a vertex
            if _segments_cross(*edges[i], *edges[j]):
                return True
    return False
