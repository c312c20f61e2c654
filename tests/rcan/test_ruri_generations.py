"""Issue 24 item 6: the RCAN 2.1+ RURI (with a version segment) beside the 1.2 form.

The official SDK's `RobotURI` is the oracle of the 2.1+ grammar.
"""

from __future__ import annotations

import pytest
from rcan.address import RobotURI

from rcan_rtps.rcan import InvalidRuriError, parse_ruri

V21 = [
    "rcan://registry.local/rcan-rtps/simbot/v1/sim-0001",
    "rcan://registry.rcan.dev/acme/robotarm/v2/unit-001",
    "rcan://registry.rcan.dev/continuonai/continuonbot/1.0.0/pi5-lab-01",
    "rcan://registry.local/universal-robots/ur5e/v5.1/ur5e-cell-0007",
]


@pytest.mark.parametrize("text", V21)
def test_the_sdks_ruris_parse_the_same(text: str) -> None:
    ours, sdk = parse_ruri(text), RobotURI.parse(text)
    assert (ours.registry, ours.manufacturer, ours.model, ours.version, ours.device_id) == (
        sdk.registry, sdk.manufacturer, sdk.model, sdk.version, sdk.device_id)
    assert str(ours) == str(sdk) == text


def test_port_and_capability_in_the_2_1_form() -> None:
    ruri = parse_ruri("rcan://registry.local/acme/bot/v2/unit-0001:9000/arm")
    assert (ruri.version, ruri.device_id, ruri.port, ruri.capability) == (
        "v2", "unit-0001", 9000, "arm")
    assert str(ruri) == "rcan://registry.local/acme/bot/v2/unit-0001:9000/arm"


@pytest.mark.parametrize(("text", "device_id", "capability"), [
    # an all-digit 1.2 device-id is not a version: a 1.2 RURI with a capability
    ("rcan://local.rcan/acme/bot/12345678/arm", "12345678", "arm"),
    ("rcan://local.rcan/unitree/go2/a1b2c3d4:9000/teleop", "a1b2c3d4", "teleop"),
])
def test_the_1_2_form_with_a_capability_is_still_1_2(text: str, device_id: str,
                                                      capability: str) -> None:
    ruri = parse_ruri(text)
    assert (ruri.version, ruri.device_id, ruri.capability) == (None, device_id, capability)


@pytest.mark.parametrize(("text", "rule"), [
    ("rcan://registry.local/acme/bot/v2/short", "at least 8"),  # device-id rule
    ("rcan://registry.local/acme/bot/v2", "at least 8"),  # read as 1.2: device-id v2
    ("rcan://registry.local/acme/bot/v2/unit-0001?sig=abc", "expected"),
    ("rcan://registry.local/Acme/bot/v2/unit-0001", "lowercase"),
])
def test_bad_2_1_ruris_say_why(text: str, rule: str) -> None:
    with pytest.raises(InvalidRuriError) as info:
        parse_ruri(text)
    assert rule in info.value.rule


def test_the_same_robot_with_and_without_a_version() -> None:
    v1 = parse_ruri("rcan://registry.local/acme/bot/v1/unit-0001").robot
    v2 = parse_ruri("rcan://registry.local/acme/bot/v2/unit-0001").robot
    bare = parse_ruri("rcan://registry.local/acme/bot/unit-0001:8000/arm").robot
    assert v1 == bare and bare == v2  # a 1.2 address reaches the robot whatever its version
    assert v1 != v2  # two versions are two robots
    assert v1 == "rcan://registry.local/acme/bot/unit-0001"
    assert v1 != parse_ruri("rcan://registry.local/acme/bot/v1/unit-0002").robot
    assert hash(v1) == hash(bare)
