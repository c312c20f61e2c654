"""What `topic echo`/`pub` say when a topic's endpoints carry another type than asked for:
the name and RIHS01 hash of both sides (the graph here is data; the wire is in
tests/interop/test_cli_wrong_use.py)."""

from __future__ import annotations

import pytest

from rcan_rtps.cli._common import type_conflict
from rcan_rtps.ros import qos
from rcan_rtps.ros.graph import Direction, Endpoint
from rcan_rtps.ros.names import EndpointKind
from rcan_rtps.ros.typesys.store import TypeStore

pytestmark = pytest.mark.offline
STORE = TypeStore(distro="jazzy")
STRING, INT32 = "std_msgs/msg/String", "std_msgs/msg/Int32"


def _endpoint(type_name: str, type_hash: str, node: str = "talker") -> Endpoint:
    return Endpoint(Direction.PUBLISHER, EndpointKind.TOPIC, "/chatter", type_name,
                    "rt/chatter", type_name.replace("/", "::"), b"\x01" * 16, b"\x01" * 16,
                    qos.DEFAULT, type_hash, "eProsima Fast DDS", node, "/")


def test_another_name_is_named_with_both_hashes() -> None:
    theirs = _endpoint(STRING, STORE.hash_of(STRING))
    problem = type_conflict(STORE, "me", [theirs], "/chatter", INT32)
    assert problem is not None
    short = {name: "RIHS01 " + STORE.hash_of(name).removeprefix("RIHS01_")[:12] + "…"
             for name in (STRING, INT32)}
    assert problem == (f"type mismatch: /chatter has {STRING} ({short[STRING]}), "
                            f"you asked for {INT32} ({short[INT32]})")


def test_the_same_name_with_another_definition_is_a_mismatch() -> None:
    changed = "RIHS01_" + "ab" * 32
    problem = type_conflict(STORE, "me", [_endpoint(STRING, changed)], "/chatter",
                            "std_msgs/String")
    assert problem is not None
    assert f"has {STRING} (RIHS01 abababababab…), you asked for {STRING} (RIHS01 " in problem


def test_the_same_type_or_an_unknown_hash_or_our_own_endpoint_is_no_mismatch() -> None:
    same = _endpoint(STRING, STORE.hash_of(STRING))
    no_hash = _endpoint(STRING, "")  # a peer that announces none (Humble): names only
    ours = _endpoint(INT32, STORE.hash_of(INT32), node="me")
    assert type_conflict(STORE, "me", [same, no_hash, ours], "/chatter", STRING) is None
