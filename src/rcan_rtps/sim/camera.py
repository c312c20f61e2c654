"""The simulated robot's overhead camera: a small top-down view of the floor, as
sensor_msgs/Image (rgb8) on `camera/image_raw`, twice a second.

What it shows is drawn from the sim's own state, so a client that looks at it sees the robot
where odometry says it is: a light floor with a line every metre, darker axes through the
origin, and the robot as a red square with a short dark stroke towards its heading. The view
is centred on the origin, `SCALE_PX_PER_M` pixels to the metre.
"""

from __future__ import annotations

import asyncio
import contextlib
import math

from ..ros.participant import RosNode
from ..ros.rostime import now_msg
from .robot import SimRobot

TOPIC = "camera/image_raw"
WIDTH, HEIGHT = 160, 120
SCALE_PX_PER_M = 8.0
PERIOD_S = 0.5
FLOOR, GRID, AXIS = (232, 232, 232), (200, 200, 200), (140, 140, 140)
ROBOT, HEADING = (220, 30, 30), (40, 40, 40)


def _floor() -> bytearray:
    """The empty floor, drawn once: every frame starts as a copy of it."""
    pixels = bytearray(bytes(FLOOR) * (WIDTH * HEIGHT))
    cx, cy = WIDTH // 2, HEIGHT // 2
    for u in range(WIDTH):
        for v in range(HEIGHT):
            on_x, on_y = (u - cx) % SCALE_PX_PER_M == 0, (v - cy) % SCALE_PX_PER_M == 0
            if u == cx or v == cy:
                _put(pixels, u, v, AXIS)
            elif on_x or on_y:
                _put(pixels, u, v, GRID)
    return pixels


def _put(pixels: bytearray, u: int, v: int, rgb: tuple[int, int, int]) -> None:
    if 0 <= u < WIDTH and 0 <= v < HEIGHT:
        i = (v * WIDTH + u) * 3
        pixels[i:i + 3] = bytes(rgb)


def pixel_of(x: float, y: float) -> tuple[int, int]:
    """Where a point of the floor (m, map frame: x right, y up) is in the image."""
    return (round(WIDTH // 2 + x * SCALE_PX_PER_M), round(HEIGHT // 2 - y * SCALE_PX_PER_M))


def render(floor: bytes, x: float, y: float, yaw: float) -> bytes:
    pixels = bytearray(floor)
    u0, v0 = pixel_of(x, y)
    for du in range(-2, 3):
        for dv in range(-2, 3):
            _put(pixels, u0 + du, v0 + dv, ROBOT)
    for step in range(3, 7):
        _put(pixels, round(u0 + step * math.cos(yaw)), round(v0 - step * math.sin(yaw)),
             HEADING)
    return bytes(pixels)


class SimCamera:
    def __init__(self, node: RosNode, robot: SimRobot) -> None:
        self._robot = robot
        self._floor = bytes(_floor())
        self.publisher = node.create_publisher(TOPIC, "sensor_msgs/msg/Image")

    def publish(self) -> None:
        s = self._robot.state
        self.publisher.publish({
            "header": {"stamp": now_msg(), "frame_id": "overhead_camera"},
            "height": HEIGHT, "width": WIDTH, "encoding": "rgb8", "is_bigendian": 0,
            "step": WIDTH * 3, "data": render(self._floor, s.x, s.y, s.yaw)})

    async def run(self, stop: asyncio.Event) -> None:
        while not stop.is_set():
            self.publish()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), PERIOD_S)
