"""ROS names: validation with the rule that broke, expansion, and DDS (de)mangling.

Rules follow rcl/rmw: names hold letters, digits, `_` and `/`; no empty tokens (`//`),
no trailing `/`, no token starting with a digit; `~` only as the first character, and
then followed by `/` (except in a two-character name, as in rcl); node names are a
single token. `~` expands to the node's fully qualified name. Topic `/a/b` is DDS topic
`rt/a/b`; service `/s` is `rq/sRequest` + `rr/sReply`; action `/x` lives under
`/x/_action/…`.
"""

from __future__ import annotations

import enum
import re

import msgspec

from .errors import InvalidNameError

MAX_TOPIC_LENGTH = 247  # RMW_TOPIC_MAX_NAME_LENGTH: 255 minus room for DDS prefixes
MAX_NODE_NAME_LENGTH = 255
MAX_NAMESPACE_LENGTH = MAX_TOPIC_LENGTH - 2  # room for "/" and a one-character name

_TOKEN_CHAR = re.compile(r"[A-Za-z0-9_]")
_SUBSTITUTION = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")

TOPIC_PREFIX = "rt"
REQUEST_PREFIX = "rq"
REPLY_PREFIX = "rr"
ACTION_INFIX = "/_action/"
ACTION_SERVICES = ("send_goal", "get_result", "cancel_goal")
ACTION_TOPICS = ("feedback", "status")


def _check_chars(name: str, allowed_extra: str) -> None:
    for i, ch in enumerate(name):
        if not (_TOKEN_CHAR.match(ch) or ch in allowed_extra):
            raise InvalidNameError(
                name, "must contain only letters, digits, '_' and '/'" +
                (" (and '~' at the start)" if "~" in allowed_extra else ""), i)


def _check_tokens(name: str) -> None:
    if "//" in name:
        raise InvalidNameError(name, "must not contain repeated '/'", name.index("//"))
    offset = 0
    for token in name.split("/"):
        if token and token[0].isdigit():
            raise InvalidNameError(name, "tokens must not start with a digit", offset)
        offset += len(token) + 1


def validate_topic_name(name: str) -> None:
    """Validates a topic or service name as given by a user (may be relative, `~`)."""
    if not name:
        raise InvalidNameError(name, "must not be empty")
    body = _SUBSTITUTION.sub("x", name)
    if "{" in body or "}" in body:
        raise InvalidNameError(name, "substitutions must be balanced '{name}'", body.find("{"))
    _check_chars(body, "/~")
    if "~" in body[1:]:
        raise InvalidNameError(name, "'~' is allowed only at the start", body.index("~", 1))
    # rcl checks this only in names of three characters or more: `~x` passes and expands
    # to the node's name plus `x` (node /ns/n: `/ns/nx`); we resolve the same names it does.
    if name.startswith("~") and len(name) > 2 and name[1] != "/":
        raise InvalidNameError(name, "'~' must be followed by '/'", 1)
    if body.endswith("/") and body != "/":
        raise InvalidNameError(name, "must not end with '/'", len(body) - 1)
    if body == "/":
        raise InvalidNameError(name, "must not be just '/'")
    _check_tokens(body)


def validate_full_name(name: str) -> None:
    """Validates a fully qualified topic or service name (`/a/b`)."""
    if not name.startswith("/"):
        raise InvalidNameError(name, "a fully qualified name must start with '/'", 0)
    validate_topic_name(name)
    if "{" in name or "~" in name:
        raise InvalidNameError(name, "a fully qualified name has no '~' or substitutions")
    if len(name) > MAX_TOPIC_LENGTH:
        raise InvalidNameError(name, f"must not be longer than {MAX_TOPIC_LENGTH} characters")


def validate_node_name(name: str) -> None:
    if not name:
        raise InvalidNameError(name, "a node name must not be empty")
    for i, ch in enumerate(name):
        if not _TOKEN_CHAR.match(ch):
            raise InvalidNameError(name, "a node name holds only letters, digits and '_'", i)
    if name[0].isdigit():
        raise InvalidNameError(name, "a node name must not start with a digit", 0)
    if len(name) > MAX_NODE_NAME_LENGTH:
        raise InvalidNameError(name, f"a node name is at most {MAX_NODE_NAME_LENGTH} characters")


def validate_namespace(namespace: str) -> None:
    if not namespace:
        raise InvalidNameError(namespace, "a namespace must not be empty")
    if not namespace.startswith("/"):
        raise InvalidNameError(namespace, "a namespace must be absolute (start with '/')", 0)
    if namespace == "/":
        return
    _check_chars(namespace, "/")
    if namespace.endswith("/"):
        raise InvalidNameError(namespace, "must not end with '/'", len(namespace) - 1)
    _check_tokens(namespace)
    if len(namespace) > MAX_NAMESPACE_LENGTH:
        raise InvalidNameError(namespace, f"must not be longer than {MAX_NAMESPACE_LENGTH}")


def normalize_namespace(namespace: str) -> str:
    """`robot1` → `/robot1`, `` → `/`: what rclpy does with a node's namespace."""
    namespace = namespace.strip() or "/"
    if not namespace.startswith("/"):
        namespace = "/" + namespace
    if len(namespace) > 1:
        namespace = namespace.rstrip("/") or "/"
    validate_namespace(namespace)
    return namespace


def expand_topic_name(name: str, node_name: str, namespace: str) -> str:
    """Resolves a relative, `~` or substituted name against a node, as rcl does."""
    validate_topic_name(name)
    validate_node_name(node_name)
    validate_namespace(namespace)
    base = namespace.rstrip("/")
    substitutions = {"node": node_name, "ns": namespace, "namespace": namespace}

    def substitute(m: re.Match[str]) -> str:
        key = m.group(1)
        if key not in substitutions:
            raise InvalidNameError(name, f"unknown substitution '{{{key}}}'", m.start())
        return substitutions[key]

    expanded = _SUBSTITUTION.sub(substitute, name)
    if expanded.startswith("~"):  # `~`, `~/x`, `~x`: the node's fully qualified name first
        expanded = f"{base}/{node_name}{expanded[1:]}"
    elif not expanded.startswith("/"):
        expanded = f"{base}/{expanded}"
    expanded = re.sub(r"/+", "/", expanded)  # `{ns}` next to '/' may double a separator
    validate_full_name(expanded)
    return expanded


class EndpointKind(enum.Enum):
    TOPIC = "topic"
    REQUEST = "request"
    REPLY = "reply"


class Demangled(msgspec.Struct, frozen=True):
    kind: EndpointKind
    name: str  # the ROS name: topic or service


def mangle_topic(name: str) -> str:
    validate_full_name(name)
    return TOPIC_PREFIX + name


def mangle_service(name: str) -> tuple[str, str]:
    """`/s` → (`rq/sRequest`, `rr/sReply`)."""
    validate_full_name(name)
    return f"{REQUEST_PREFIX}{name}Request", f"{REPLY_PREFIX}{name}Reply"


def demangle(dds_topic: str) -> Demangled | None:
    """The ROS view of a DDS topic name, or None for non-ROS topics."""
    if dds_topic.startswith(TOPIC_PREFIX + "/"):
        return Demangled(EndpointKind.TOPIC, dds_topic[len(TOPIC_PREFIX):])
    if dds_topic.startswith(REQUEST_PREFIX + "/") and dds_topic.endswith("Request"):
        return Demangled(EndpointKind.REQUEST, dds_topic[len(REQUEST_PREFIX):-len("Request")])
    if dds_topic.startswith(REPLY_PREFIX + "/") and dds_topic.endswith("Reply"):
        return Demangled(EndpointKind.REPLY, dds_topic[len(REPLY_PREFIX):-len("Reply")])
    return None


def action_names(action: str) -> dict[str, str]:
    """The five ROS names an action uses, keyed by role."""
    validate_full_name(action)
    return {part: f"{action}{ACTION_INFIX}{part}" for part in (*ACTION_SERVICES, *ACTION_TOPICS)}


def action_of(name: str) -> tuple[str, str] | None:
    """`/nav/_action/status` → (`/nav`, `status`); None when not an action member."""
    head, sep, part = name.rpartition(ACTION_INFIX)
    if sep and head and part in (*ACTION_SERVICES, *ACTION_TOPICS):
        return head, part
    return None


def is_hidden(name: str) -> bool:
    """Hidden like ros2cli: any token starting with '_'."""
    return any(token.startswith("_") for token in name.split("/") if token)
