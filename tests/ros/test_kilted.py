"""ROS 2 Kilted as a second real graph: hashes and a topic round trip (when it installed)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from oracle.client import RclpyOracle

from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.typesys.store import TypeStore


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


async def test_kilted_rclpy_receives_our_twist(kilted_python: Path, domain_id: int) -> None:
    with RclpyOracle(kilted_python, "kilted_oracle", domain_id=domain_id) as oracle, \
            RosNode("rcan_bridge", "/k", domain_id=domain_id, distro="kilted") as node:
        oracle.call("subscribe", topic="/k/cmd_vel", type="geometry_msgs/msg/Twist")
        pub = node.create_publisher("cmd_vel", "geometry_msgs/msg/Twist")
        await pub.wait_for_subscribers(1, timeout=15)
        pub.publish({"linear": {"x": 0.3}})
        got = []
        for _ in range(100):
            got = oracle.call("take", topic="/k/cmd_vel")
            if got:
                break
            await asyncio.sleep(0.05)
        assert got and got[0]["linear"]["x"] == 0.3
        # Kilted's rclpy does not yet list our node from ros_discovery_info (Jazzy does);
        # tracked on the issue as open work rather than asserted here.
