"""ROS 2 Kilted as a second real graph: hashes and a topic round trip (when it installed)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from oracle.client import RclpyOracle
from waiting import eventually, take

from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.typesys.store import TypeStore

from .offline_data import DATA, TEST_IDL, load


def test_bundle_hashes_match_kilted(kilted_python: Path) -> None:
    share = kilted_python.parent.parent / "share"
    store = TypeStore(distro="kilted")
    compared, wrong = 0, []
    for interface in store.interface_names():
        pkg, kind, name = interface.split("/")
        path = share / pkg / kind / f"{name}.json"
        if not path.exists():
            continue
        for entry in json.loads(path.read_text())["type_hashes"]:
            if entry["type_name"].startswith(interface):
                compared += 1
                if store.hash_of(entry["type_name"]) != entry["hash_string"]:
                    wrong.append(entry["type_name"])
    assert not wrong
    assert compared > 100


def test_kilted_overrides_hash_as_the_kilted_generator_says(kilted_python: Path,
                                                             tmp_path: Path) -> None:
    """nav2_msgs at its Kilted release, with the packages not on PyPI it needs, through the
    official Kilted generator: every hash equals ours under `--distro kilted`."""
    out = tmp_path / "kilted.json"
    subprocess.run([str(kilted_python), str(DATA / "make_rihs01_official.py"), "--interfaces",
                    str(DATA / "interfaces"), str(DATA / "interfaces_distro/kilted"),
                    "--out", str(out)], check=True, capture_output=True, timeout=300)
    official = json.loads(out.read_text(encoding="utf-8"))["hashes"]
    store = TypeStore(distro="kilted")
    assert [n for n, h in official.items() if store.hash_of(n) != h] == []
    jazzy = load("rihs01_official_jazzy.json")["hashes"]
    assert len([n for n, h in official.items() if jazzy.get(n) != h]) > 20  # overrides matter


async def test_kilted_rclpy_receives_and_lists_us(kilted_python: Path, domain_id: int) -> None:
    with RclpyOracle(kilted_python, "kilted_oracle", domain_id=domain_id) as oracle, \
            RosNode("rcan_bridge", "/k", domain_id=domain_id, distro="kilted") as node:
        await oracle.acall("subscribe", topic="/k/cmd_vel", type="geometry_msgs/msg/Twist")
        pub = node.create_publisher("cmd_vel", "geometry_msgs/msg/Twist")
        await pub.wait_for_subscribers(1, timeout=15)
        pub.publish({"linear": {"x": 0.3}})
        got = await take(oracle, "/k/cmd_vel")
        assert got and got[0]["linear"]["x"] == 0.3

        async def listed() -> bool:
            return ["rcan_bridge", "/k"] in await oracle.acall("node_names")

        await eventually(listed)


async def test_kilted_sequences_both_ways(kilted_python: Path, domain_id: int) -> None:
    """Types with sequences match Fast DDS 3 (Kilted) too: XTypes info is not in the way."""
    with RclpyOracle(kilted_python, "kilted_oracle", domain_id=domain_id) as oracle, \
            RosNode("peer", "/k", domain_id=domain_id, distro="kilted") as node:
        sub = node.create_subscription("/k/joint_states", "sensor_msgs/msg/JointState")
        await oracle.acall("publisher", topic="/k/joint_states", type="sensor_msgs/msg/JointState")
        await sub.wait_for_publishers(1, timeout=15)
        await oracle.acall("wait_subscribers", topic="/k/joint_states")
        await oracle.acall("publish", topic="/k/joint_states", type="sensor_msgs/msg/JointState",
                           value={"name": ["a", "b"], "position": [0.5, 1.5]}, count=3)
        got = await sub.get(timeout=10)
        assert list(got.name) == ["a", "b"] and list(got.position) == [0.5, 1.5]
        await oracle.acall("subscribe", topic="/k/diagnostics",
                           type="diagnostic_msgs/msg/DiagnosticArray")
        pub = node.create_publisher("/k/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
        await pub.wait_for_subscribers(1, timeout=15)
        await oracle.acall("wait_publishers", topic="/k/diagnostics")
        pub.publish({"status": [{"level": 2, "name": "motor", "message": "hot"}]})
        received = await take(oracle, "/k/diagnostics")
        assert received and received[0]["status"][0]["message"] == "hot"


async def test_kilted_wstrings_both_ways(kilted_python: Path, domain_id: int) -> None:
    """wstring (Fast DDS 3): the same UTF-16-units-as-uint32 wire as Jazzy, both ways."""
    text = "Hellö 😀"
    with RclpyOracle(kilted_python, "kilted_oracle", domain_id=domain_id) as oracle, \
            RosNode("peer", "/k", domain_id=domain_id, distro="kilted",
                    idl_paths=[TEST_IDL]) as node:
        sub = node.create_subscription("/k/wide_in", "test_msgs/msg/WStrings")
        await oracle.acall("publisher", topic="/k/wide_in", type="test_msgs/msg/WStrings")
        await sub.wait_for_publishers(1, timeout=15)
        await oracle.acall("wait_subscribers", topic="/k/wide_in")
        await oracle.acall("publish", topic="/k/wide_in", type="test_msgs/msg/WStrings",
                           value={"wstring_value": text}, count=3)
        got = node.values.to_plain("test_msgs/msg/WStrings", await sub.get(timeout=10))
        assert got["wstring_value"] == text and got["wstring_value_default3"] == "ハローワールド"
        await oracle.acall("subscribe", topic="/k/wide_out", type="test_msgs/msg/WStrings")
        pub = node.create_publisher("/k/wide_out", "test_msgs/msg/WStrings")
        await pub.wait_for_subscribers(1, timeout=15)
        await oracle.acall("wait_publishers", topic="/k/wide_out")
        pub.publish({"wstring_value": text, "unbounded_sequence_of_wstrings": [text, ""]})
        received = await take(oracle, "/k/wide_out")
        assert received and received[0]["wstring_value"] == text
        assert received[0]["unbounded_sequence_of_wstrings"] == [text, ""]


async def test_kilted_services_and_actions_from_fresh_clients(kilted_python: Path,
                                                              domain_id: int) -> None:
    """Kilted (Fast DDS 3) servers: every reply and every first feedback reaches a fresh
    client of ours, each checked against its own request."""
    from rcan_rtps.ros.actions import ActionClient, GoalState
    from rcan_rtps.ros.services import RequestMapping, ServiceClient

    with RclpyOracle(kilted_python, "kilted_oracle", domain_id=domain_id) as oracle, \
            RosNode("peer", "/", domain_id=domain_id, distro="kilted",
                    idl_paths=[TEST_IDL]) as node:
        await oracle.acall("echo_server", name="/echo")
        await oracle.acall("action_server", name="/fib", period=0.01)
        for i in range(20):
            client = ServiceClient(node, "/echo", "test_msgs/srv/BasicTypes")
            reply = await client.call({"string_value": f"call {i}", "int64_value": i},
                                      timeout=10)
            assert (reply.string_value, reply.int64_value) == (f"call {i}", i)
            assert client.resolve_mapping() is RequestMapping.FASTDDS
            client.close()
        for order in range(2, 8):
            actions = ActionClient(node, "/fib", "test_msgs/action/Fibonacci")
            goal = await actions.send_goal({"order": order}, timeout=10)
            assert goal.accepted
            async for feedback in goal.feedback(timeout=10):
                assert list(feedback.sequence) == [0, 1, 1]  # the first, never lost
                break
            outcome = await goal.result(timeout=10)
            assert outcome.state is GoalState.SUCCEEDED and outcome.result is not None
            assert len(outcome.result.sequence) == order + 1
            actions.close()
