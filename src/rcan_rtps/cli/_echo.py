"""How `topic echo` shows a message: a field of it, as YAML, JSON or CSV; and its QoS."""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import yaml
from cyclonedds.idl import IdlStruct

from ..ros import qos as qos_mod
from ..ros.errors import ValueFitError
from ..ros.graph import Endpoint
from ..ros.typesys.model import FieldType
from ..ros.typesys.store import TypeStore
from ..ros.typesys.values import MessageValues

# "best_available" adapts to the publishers found (ros2's default for echo);
# "system_default" is what rmw_cyclonedds takes as the DDS default.
RELIABILITY_CHOICES = ("best_available", "system_default", "reliable", "best_effort")
DURABILITY_CHOICES = ("best_available", "system_default", "transient_local", "volatile")
HISTORY_CHOICES = ("system_default", "keep_last", "keep_all")


def add_qos_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--qos-profile", choices=sorted(qos_mod.PRESETS), default=None,
                        help="start from this QoS preset (default: adapt to the publishers)")
    parser.add_argument("--qos-depth", type=int, default=None, metavar="N",
                        help="queue depth of a keep_last history (overrides the profile)")
    parser.add_argument("--qos-history", choices=HISTORY_CHOICES, default=None,
                        help="history policy (overrides the profile)")
    parser.add_argument("--qos-reliability", choices=RELIABILITY_CHOICES, default=None,
                        help="reliability (overrides the profile; best_available: reliable "
                        "unless a publisher is best effort)")
    parser.add_argument("--qos-durability", choices=DURABILITY_CHOICES, default=None,
                        help="durability (overrides the profile; best_available: "
                        "transient_local when every publisher offers it)")


def adapted_qos(pubs: list[Endpoint]) -> qos_mod.QosProfile:
    """Like ros2 topic echo: as strict as every publisher allows."""
    profile = qos_mod.DEFAULT
    if pubs and any(p.qos.reliability is qos_mod.Reliability.BEST_EFFORT for p in pubs):
        profile = profile.with_(reliability=qos_mod.Reliability.BEST_EFFORT)
    if pubs and all(p.qos.durability is qos_mod.Durability.TRANSIENT_LOCAL for p in pubs):
        profile = profile.with_(durability=qos_mod.Durability.TRANSIENT_LOCAL)
    return profile


def chosen_qos(args: argparse.Namespace, pubs: list[Endpoint]) -> qos_mod.QosProfile:
    """The subscription's QoS: a preset or the adapted one, then each `--qos-*` override."""
    adapted = adapted_qos(pubs)
    profile = qos_mod.preset(args.qos_profile) if args.qos_profile else adapted
    if args.qos_history == "keep_all":
        profile = profile.with_(history=qos_mod.History.KEEP_ALL)
    elif args.qos_history is not None:
        profile = profile.with_(history=qos_mod.History.KEEP_LAST)
    if args.qos_depth is not None:
        profile = profile.with_(depth=args.qos_depth)
    reliability = {"best_available": adapted.reliability,
                   "system_default": qos_mod.Reliability.RELIABLE}
    if args.qos_reliability is not None:
        profile = profile.with_(reliability=reliability.get(
            args.qos_reliability, qos_mod.Reliability(args.qos_reliability)))
    durability = {"best_available": adapted.durability,
                  "system_default": qos_mod.Durability.VOLATILE}
    if args.qos_durability is not None:
        profile = profile.with_(durability=durability.get(
            args.qos_durability, qos_mod.Durability(args.qos_durability)))
    return profile


def field_type_at(store: TypeStore, type_name: str, path: str) -> FieldType:
    """The type of the field at dotted `path`, checked before anything is subscribed."""
    current: str | None = type_name
    found: FieldType | None = None
    for part in path.split("."):
        if current is None:
            raise ValueFitError(path, f"{part!r} is inside a field that is not a message")
        msg = store.message(current)
        field = next((f for f in msg.fields if f.name == part), None)
        if field is None:
            names = ", ".join(f.name for f in msg.fields)
            raise ValueFitError(path, f"{msg.name} has no field {part!r} (fields: {names})")
        found = field.type
        current = None if found.is_collection else found.nested
    assert found is not None
    return found


class EchoFormat:
    """Turns each received message into the text `topic echo` prints for it."""

    def __init__(self, args: argparse.Namespace, values: MessageValues, type_name: str) -> None:
        self.values, self.type_name = values, type_name
        self.field: str | None = args.field
        self.no_arr: bool = args.no_arr
        self.style = "csv" if args.csv else "json" if args.json else "yaml"
        self.field_type = (field_type_at(values.types.store, type_name, args.field)
                           if args.field else None)

    def text(self, message: IdlStruct) -> str:
        return _render(self._plain(message), self.style)

    def _plain(self, message: IdlStruct) -> Any:
        if self.field is None or self.field_type is None:
            return self.values.to_plain(self.type_name, message, no_arr=self.no_arr)
        value: Any = message
        for part in self.field.split("."):
            value = getattr(value, part)
        return self.values.field_to_plain(self.field_type, value, no_arr=self.no_arr)


def _render(plain: Any, style: str) -> str:
    if style == "csv":
        return _csv(plain)
    if style == "json":
        return to_json(plain)
    if isinstance(plain, (dict, list)):
        return yaml.safe_dump(plain, sort_keys=False, allow_unicode=True) + "---"
    return f"{plain}\n---"


def _csv(plain: Any) -> str:
    """Every leaf value in field order, comma-separated (rosidl's message_to_csv shape)."""
    if isinstance(plain, dict):
        return ",".join(_csv(v) for v in plain.values())
    if isinstance(plain, list):
        return ",".join(_csv(v) for v in plain)
    return str(plain)


def to_json(plain: Any) -> str:
    """Strict JSON: NaN and ±infinity (which json.dumps writes bare, and JSON lacks) become
    the strings "NaN", "Infinity", "-Infinity" — protobuf's JSON spelling, which float()
    and JavaScript's Number() read back; null would lose which one it was."""
    try:
        return json.dumps(plain, default=str, allow_nan=False)
    except ValueError:  # rare: only then walk the message
        return json.dumps(_finite_or_named(plain), default=str, allow_nan=False)


def _finite_or_named(plain: Any) -> Any:
    if isinstance(plain, float) and not math.isfinite(plain):
        return "NaN" if math.isnan(plain) else "Infinity" if plain > 0 else "-Infinity"
    if isinstance(plain, dict):
        return {key: _finite_or_named(value) for key, value in plain.items()}
    if isinstance(plain, (list, tuple)):
        return [_finite_or_named(value) for value in plain]
    return plain
