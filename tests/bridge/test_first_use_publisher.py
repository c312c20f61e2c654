"""A command topic's writer made by its first use (bridge/commands.py `FirstUsePublisher`,
issue 27: idle memory): nothing is made before, a type nobody can resolve still fails where
the publisher is declared (the bridge's start), and the writer, once made, is the one kept."""

from __future__ import annotations

import pytest

from rcan_rtps.bridge.commands import FirstUsePublisher
from rcan_rtps.ros import qos
from rcan_rtps.ros.errors import UnknownTypeError
from rcan_rtps.ros.participant import RosNode

TRAJECTORY = "trajectory_msgs/msg/JointTrajectory"


def test_nothing_is_made_before_the_first_use(domain_id: int) -> None:
    with RosNode("rcan_bridge", "/robot1", domain_id=domain_id) as node:
        arm = FirstUsePublisher(node, "left_arm/joint_trajectory", TRAJECTORY, qos.DEFAULT)
        assert arm.topic == "/robot1/left_arm/joint_trajectory"  # known from the start
        assert not arm.made  # in the graph: tests/interop/test_arms.py
        assert arm.matched_count() == 0
        assert arm.made
        made = arm.publisher()
        assert made.topic == arm.topic and made.type_name == TRAJECTORY
        assert arm.publisher() is made


def test_an_unknown_type_fails_where_it_is_declared(domain_id: int) -> None:
    with RosNode("rcan_bridge", "/robot1", domain_id=domain_id) as node, \
            pytest.raises(UnknownTypeError):
        FirstUsePublisher(node, "arm/joint_trajectory", "trajectory_msgs/msg/NoSuchType",
                          qos.DEFAULT)
