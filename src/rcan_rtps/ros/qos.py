"""ROS 2 QoS profiles, their presets, DDS translation and compatibility checks."""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace
from typing import Any

from cyclonedds.core import Policy
from cyclonedds.qos import Qos
from cyclonedds.util import duration

from . import _cyclone_qos  # noqa: F401  (the binding's QoS getters, made not to leak)
from .errors import QosError

_UNLIMITED = -1  # DDS_LENGTH_UNLIMITED

# DDS QoS policy ids (as in an incompatible-QoS status' last_policy_id) → the names
# rclpy's warnings use.
_POLICY_NAMES = {
    2: "DURABILITY", 3: "PRESENTATION", 4: "DEADLINE", 5: "LATENCY_BUDGET", 6: "OWNERSHIP",
    8: "LIVELINESS", 10: "PARTITION", 11: "RELIABILITY", 12: "DESTINATION_ORDER", 13: "HISTORY",
    21: "LIFESPAN", 22: "DURABILITY_SERVICE", 23: "DATA_REPRESENTATION",
    24: "TYPE_CONSISTENCY_ENFORCEMENT",
}
# What Cyclone reports when the two sides' types differ (name or definition): not a QoS
# the user chose, so it is told as a type mismatch.
TYPE_CONSISTENCY_POLICY_ID = 24


def policy_name(policy_id: int) -> str:
    """`RELIABILITY_QOS_POLICY` for id 11, like rclpy's incompatible-QoS warnings."""
    return f"{_POLICY_NAMES.get(policy_id, f'UNKNOWN({policy_id})')}_QOS_POLICY"


class Reliability(enum.Enum):
    RELIABLE = "reliable"
    BEST_EFFORT = "best_effort"


class Durability(enum.Enum):
    VOLATILE = "volatile"
    TRANSIENT_LOCAL = "transient_local"


class History(enum.Enum):
    KEEP_LAST = "keep_last"
    KEEP_ALL = "keep_all"


@dataclass(frozen=True)
class QosProfile:
    history: History = History.KEEP_LAST
    depth: int = 10
    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    lifespan_s: float | None = None  # None: infinite
    deadline_s: float | None = None

    def __post_init__(self) -> None:
        if self.history is History.KEEP_LAST and self.depth < 1:
            raise QosError("keep-last history needs a depth of at least 1")

    def with_(self, **changes: Any) -> QosProfile:
        return replace(self, **changes)

    def keeping(self, depth: int) -> QosProfile:
        """This profile keeping at least `depth` samples (keep-all keeps them already). A
        reader's depth is its own: no peer matches on it."""
        if self.history is History.KEEP_ALL or self.depth >= depth:
            return self
        return replace(self, depth=depth)

    def describe(self) -> str:
        hist = f"keep_last({self.depth})" if self.history is History.KEEP_LAST else "keep_all"
        return f"{self.reliability.value}, {self.durability.value}, {hist}"

    def _dds_history(self) -> Any:
        return (Policy.History.KeepLast(self.depth) if self.history is History.KEEP_LAST
                else Policy.History.KeepAll)

    def to_dds(self, user_data: bytes | None = None) -> Qos:
        policies: list[Any] = [
            self._dds_history(),
            # rmw_cyclonedds: reliable writers block indefinitely rather than drop
            Policy.Reliability.Reliable(duration(infinite=True))
            if self.reliability is Reliability.RELIABLE else Policy.Reliability.BestEffort,
            Policy.Durability.TransientLocal if self.durability is Durability.TRANSIENT_LOCAL
            else Policy.Durability.Volatile,
            Policy.WriterDataLifecycle(autodispose=False),
            Policy.Liveliness.Automatic(duration(infinite=True)),
        ]
        if self.durability is Durability.TRANSIENT_LOCAL:
            # What a writer keeps for late joiners is the durability service's history
            # (Cyclone's default: the last sample only); rmw_cyclonedds gives it the profile's.
            policies.append(Policy.DurabilityService(
                0, self._dds_history(), _UNLIMITED, _UNLIMITED, _UNLIMITED))
        if self.lifespan_s is not None:
            policies.append(Policy.Lifespan(duration(seconds=self.lifespan_s)))
        if self.deadline_s is not None:
            policies.append(Policy.Deadline(duration(seconds=self.deadline_s)))
        if user_data is not None:
            policies.append(Policy.Userdata(user_data))
        return Qos(*policies)


# The presets of rmw/qos_profiles.h (identical in Humble, Jazzy and Kilted).
DEFAULT = QosProfile()
SENSOR_DATA = QosProfile(depth=5, reliability=Reliability.BEST_EFFORT)
SERVICES = QosProfile(depth=10)
ACTION_STATUS = QosProfile(depth=1, durability=Durability.TRANSIENT_LOCAL)
TF_STATIC = QosProfile(depth=1, durability=Durability.TRANSIENT_LOCAL)
ROSOUT = QosProfile(depth=1000, durability=Durability.TRANSIENT_LOCAL, lifespan_s=10.0)
PARAMETER_EVENTS = QosProfile(depth=1000)
DISCOVERY_INFO = QosProfile(depth=1, durability=Durability.TRANSIENT_LOCAL)

PRESETS: dict[str, QosProfile] = {
    "default": DEFAULT,
    "sensor_data": SENSOR_DATA,
    "services_default": SERVICES,
    "action_status_default": ACTION_STATUS,
    "tf_static": TF_STATIC,
    "rosout": ROSOUT,
    "parameter_events": PARAMETER_EVENTS,
    "system_default": DEFAULT,
}


def preset(name: str) -> QosProfile:
    try:
        return PRESETS[name.replace("-", "_").lower()]
    except KeyError:
        raise QosError(f"unknown QoS preset {name!r}; known: {', '.join(PRESETS)}") from None


def incompatibilities(writer: QosProfile, reader: QosProfile) -> list[str]:
    """Why a writer and a reader would silently never match (empty when they match)."""
    problems = []
    if reader.reliability is Reliability.RELIABLE and writer.reliability is not reader.reliability:
        problems.append("reader requests RELIABLE but the writer offers BEST_EFFORT")
    if (reader.durability is Durability.TRANSIENT_LOCAL
            and writer.durability is Durability.VOLATILE):
        problems.append("reader requests TRANSIENT_LOCAL but the writer offers VOLATILE")
    if reader.deadline_s is not None and (writer.deadline_s is None
                                          or writer.deadline_s > reader.deadline_s):
        problems.append("reader requests a shorter deadline than the writer offers")
    return problems


def from_dds(qos: Qos) -> QosProfile:
    """The ROS view of a discovered endpoint's DDS QoS."""
    profile = QosProfile()
    for p in qos.policies if qos is not None else ():
        if isinstance(p, Policy.History.KeepLast):
            profile = profile.with_(history=History.KEEP_LAST, depth=p.depth)
        elif p is Policy.History.KeepAll:
            profile = profile.with_(history=History.KEEP_ALL)
        elif p is Policy.Reliability.BestEffort:
            profile = profile.with_(reliability=Reliability.BEST_EFFORT)
        elif isinstance(p, Policy.Reliability.Reliable):
            profile = profile.with_(reliability=Reliability.RELIABLE)
        elif p is Policy.Durability.TransientLocal:
            profile = profile.with_(durability=Durability.TRANSIENT_LOCAL)
        elif p is Policy.Durability.Volatile:
            profile = profile.with_(durability=Durability.VOLATILE)
    return profile


# The USER_DATA key of a writer the robot obeys, naming who governs it (`RosNode.governed_by`).
GOVERNED_BY = "governed_by"


def user_data_entry(key: str, value: str) -> str:
    """`key=value;` for an entity's USER_DATA, or "" for no value. A value that would split
    the list (`;`, `=`) or does not print is refused: readers parse it as text."""
    if not value:
        return ""
    if not value.isprintable() or any(c in value for c in ";="):
        raise ValueError(f"{key}: {value!r} cannot be a USER_DATA value")
    return f"{key}={value};"


def user_data_of(qos: Qos | None) -> dict[str, str]:
    """`key=value;` pairs from an entity's USER_DATA (`typehash=…;`, `enclave=…;`)."""
    if qos is None:
        return {}
    for p in qos.policies:
        if isinstance(p, Policy.Userdata):
            text = bytes(p.data).decode("utf-8", "replace")
            pairs = (item.split("=", 1) for item in text.split(";") if "=" in item)
            return {k.strip(): v.strip() for k, v in pairs}
    return {}
