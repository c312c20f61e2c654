"""Every listed message type and every test_msgs message type crosses both ways between us and
rclpy: random values (default and sensor QoS) and each field at both ends of its range
(test_msgs); WStrings with astral characters (UTF-16 units, surrogate pairs)."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from oracle.client import RclpyOracle
from waiting import eventually, take

from rcan_rtps.ros import qos
from rcan_rtps.ros.participant import RosNode

from ..ros.offline_data import TEST_IDL
from ..ros.strategies import LISTED_TYPES, extreme_values, values_for

TEST_MSGS = ["Arrays", "BasicTypes", "BoundedPlainSequences", "BoundedSequences", "Builtins",
             "Constants", "Defaults", "Empty", "MultiNested", "Nested", "Strings",
             "UnboundedSequences", "WStrings"]
TYPES = [*LISTED_TYPES, *(f"test_msgs/msg/{name}" for name in TEST_MSGS)]
QOS = {"default": qos.DEFAULT, "sensor": qos.SENSOR_DATA}


@pytest.fixture(scope="module")
def oracle(jazzy_python: Path, module_domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_python, "types_oracle", domain_id=module_domain_id) as agent:
        yield agent


@pytest.fixture(scope="module")
def node(module_domain_id: int) -> Iterator[RosNode]:
    with RosNode("types_peer", domain_id=module_domain_id, idl_paths=[TEST_IDL]) as n:
        yield n


@pytest.mark.parametrize("qos_name", sorted(QOS))
@pytest.mark.parametrize("type_name", TYPES)
@settings(max_examples=1, deadline=None, derandomize=True, suppress_health_check=[
    HealthCheck.function_scoped_fixture, HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
async def test_both_ways(oracle: RclpyOracle, node: RosNode, type_name: str, qos_name: str,
                         data: st.DataObject) -> None:
    values = [data.draw(values_for(node.store, type_name, max_items=3)) for _ in range(3)]
    short = type_name.rsplit("/", 1)[-1].lower()
    await cross_both_ways(oracle, node, type_name, qos_name, values, f"{short}_{qos_name}")


@pytest.mark.parametrize("name", TEST_MSGS)
async def test_test_msgs_at_both_ends_of_every_range(oracle: RclpyOracle, node: RosNode,
                                                     name: str) -> None:
    type_name = f"test_msgs/msg/{name}"
    values = [extreme_values(node.store, type_name, end) for end in ("max", "min")]
    await cross_both_ways(oracle, node, type_name, "default", values, f"{name.lower()}_ends")


WIDE = ["", "a", "Hellö wörld!", "ハローワールド", "😀 needs two UTF-16 units", "\u00e9\U0001F600"]


async def test_wstrings_with_astral_characters(oracle: RclpyOracle, node: RosNode) -> None:
    values = [{"wstring_value": text, "array_of_wstrings": [text, "", "x"],
               "unbounded_sequence_of_wstrings": WIDE[: i + 1]} for i, text in enumerate(WIDE)]
    got = await cross_both_ways(oracle, node, "test_msgs/msg/WStrings", "default", values, "wide")
    assert [m["wstring_value"] for m in got] == WIDE


async def cross_both_ways(oracle: RclpyOracle, node: RosNode, type_name: str, qos_name: str,
                          values: list[Any], tag: str) -> list[Any]:
    """Sends `values` us → rclpy and rclpy → us; both sides must see what rclpy makes of them."""
    n = len(values)
    out, back = f"/both/{tag}_out", f"/both/{tag}_back"
    profile = QOS[qos_name]
    # us → rclpy
    await oracle.acall("subscribe", topic=out, type=type_name, qos=qos_name)
    pub = node.create_publisher(out, type_name, profile)
    await pub.wait_for_subscribers(1, timeout=15)
    await oracle.acall("wait_publishers", topic=out)
    await asyncio.sleep(0.2)
    for value in values:
        pub.publish(value)
        await asyncio.sleep(0.02)
    received = await take(oracle, out, until=lambda got: len(got) >= n)
    expected = [await oracle.acall("roundtrip", type=type_name, value=v) for v in values]
    assert received == expected
    # rclpy → us
    sub = node.create_subscription(back, type_name, profile)
    await oracle.acall("publisher", topic=back, type=type_name, qos=qos_name)
    await sub.wait_for_publishers(1, timeout=15)
    await oracle.acall("wait_subscribers", topic=back)
    await asyncio.sleep(0.2)
    for value in values:
        await oracle.acall("publish", topic=back, type=type_name, value=value, count=1, period=0.02)

    async def take_ours() -> list[Any]:
        items = []
        while True:
            try:
                items.append(node.values.to_plain(type_name, await sub.get(timeout=0.05)))
            except asyncio.TimeoutError:
                return items

    ours: list[Any] = []

    async def all_of_ours() -> bool:
        ours.extend(await take_ours())
        return len(ours) >= n

    await eventually(all_of_ours, what=lambda: f"{n} samples on {back}: {ours!r}")
    assert ours == expected
    return ours
