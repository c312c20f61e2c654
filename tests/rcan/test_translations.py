"""Bridge spec §4's translations, field by field: `move` → Twist ("linear.x, linear.y,
angular.z mapped from RCAN params") and `navigate` → NavigateToPose ("pose from RCAN params;
frame_id from bridge config (default: map)"). The workspace fence checks a goal in
`nav_frame_id`: a goal sent in another frame than the one checked would drive outside it."""

from __future__ import annotations

import math
from typing import Any

import pytest

from rcan_rtps.rcan.actions.move import MoveParams, velocity
from rcan_rtps.rcan.actions.navigate import NavigateParams, goal

STAMP = {"sec": 7, "nanosec": 9}


class Kit:
    """The `MessageKit` of a bridge whose `bridge.ros2.nav_frame_id` is `frame`."""

    message_type = "nav2_msgs/action/NavigateToPose"

    def __init__(self, frame: str) -> None:
        self.frame = frame

    def struct(self, type_name: str) -> Any:
        raise AssertionError("navigate builds plain data")

    def now(self) -> dict[str, int]:
        return STAMP

    def setting(self, key: str) -> Any:
        assert key == "nav_frame_id"
        return self.frame


@pytest.mark.parametrize("yaw", [0.0, math.pi / 2, -math.pi / 2, math.pi, 3.0])
def test_the_pose_is_the_params_and_the_frame_the_configs(yaw: float) -> None:
    sent = goal(NavigateParams(x=1.5, y=-2.0, yaw=yaw), Kit("map"))
    header, pose = sent["pose"]["header"], sent["pose"]["pose"]
    assert header == {"stamp": STAMP, "frame_id": "map"}
    assert pose["position"] == {"x": 1.5, "y": -2.0, "z": 0.0}
    q = pose["orientation"]
    assert (q["x"], q["y"]) == (0.0, 0.0)
    assert math.isclose(q["z"] ** 2 + q["w"] ** 2, 1.0)
    # the heading the quaternion stands for is the yaw asked (REP 103: about +z)
    heading = math.atan2(2 * q["w"] * q["z"], 1 - 2 * q["z"] ** 2)
    assert math.isclose(math.remainder(heading - yaw, math.tau), 0.0, abs_tol=1e-12)


def test_the_configured_frame_is_used_and_a_given_one_wins() -> None:
    params = NavigateParams(x=0.0, y=0.0, yaw=0.0)
    assert goal(params, Kit("site"))["pose"]["header"]["frame_id"] == "site"
    given = NavigateParams(x=0.0, y=0.0, yaw=0.0, frame_id="map")
    assert goal(given, Kit("site"))["pose"]["header"]["frame_id"] == "map"


def vector3(x: float, y: float, z: float) -> dict[str, float]:
    return {"x": x, "y": y, "z": z}


class TwistKit(Kit):
    """Message classes as plain constructors of dicts."""

    def __init__(self, message_type: str) -> None:
        super().__init__("map")
        self.message_type = message_type

    def struct(self, type_name: str) -> Any:
        if type_name == "geometry_msgs/msg/Vector3":
            return vector3
        return lambda **fields: {"type": type_name, **fields}


@pytest.mark.parametrize("stamped", [False, True])
def test_each_velocity_goes_to_its_own_twist_field(stamped: bool) -> None:
    kind = "geometry_msgs/msg/TwistStamped" if stamped else "geometry_msgs/msg/Twist"
    sent = velocity(MoveParams(linear_x=0.25, linear_y=-0.5, angular_z=0.75), TwistKit(kind))
    twist = sent["twist"] if stamped else sent
    assert twist["type"] == "geometry_msgs/msg/Twist"
    assert twist["linear"] == {"x": 0.25, "y": -0.5, "z": 0.0}
    assert twist["angular"] == {"x": 0.0, "y": 0.0, "z": 0.75}
    if stamped:
        assert sent["type"] == kind and sent["header"]["stamp"]["sec"] == STAMP["sec"]
