"""Camera frames from real rclpy publishers (Fast DDS and Cyclone DDS), shown as files: a raw
Image as a PNG with its exact pixels, a CompressedImage as the JPEG it carried; the newest
frame wins; nothing before the first frame. Then the sim's overhead camera through the
bridge, over REST and as an MCP resource, with the robot drawn where odometry says it is."""

from __future__ import annotations

import base64
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import pytest
from mcp_types import BlobResourceContents
from oracle.client import OracleEnv, RclpyOracle, both_rmws
from pngcheck import read_png
from waiting import eventually

from rcan_rtps.api.ports import ImageUnavailable
from rcan_rtps.bridge.images import ImageFeeds
from rcan_rtps.config import ImageFeedConfig
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.sim.camera import HEIGHT, ROBOT, WIDTH, pixel_of
from tests.interop.test_demo import Demo, call, wait_status
from tests.interop.test_mcp_sim import agent

FEEDS = {"front": ImageFeedConfig(topic="/cam/front"),
         "jpeg": ImageFeedConfig(topic="/cam/jpeg", type="sensor_msgs/msg/CompressedImage")}


@pytest.fixture
def oracle(jazzy_oracle: OracleEnv, domain_id: int) -> Iterator[RclpyOracle]:
    with RclpyOracle(jazzy_oracle, "camera_node", "/", domain_id=domain_id) as agent:
        yield agent


@pytest.fixture
def node(domain_id: int) -> Iterator[RosNode]:
    with RosNode("rcan_bridge", "/", domain_id=domain_id, distro="jazzy") as n:
        yield n


def frame_data(shade: int) -> bytes:
    return bytes((shade + i) % 256 for i in range(4 * 3 * 3))  # 4x3 rgb8


@both_rmws
async def test_rclpy_frames_are_shown_as_files(oracle: RclpyOracle, node: RosNode) -> None:
    feeds = ImageFeeds(node, FEEDS)
    try:
        with pytest.raises(ImageUnavailable) as nothing:
            await feeds.frame("front")
        assert nothing.value.reason == "no_frame_yet"
        for topic, kind in (("/cam/front", "Image"), ("/cam/jpeg", "CompressedImage")):
            await oracle.acall("publisher", topic=topic, type=f"sensor_msgs/msg/{kind}",
                               qos="sensor")
        for subscription in feeds._subscriptions:
            await subscription.wait_for_publishers(1, timeout=15)
        for shade in (0, 100):  # two frames: the newest is shown
            await oracle.acall("publish", topic="/cam/front", type="sensor_msgs/msg/Image",
                               value={"height": 3, "width": 4, "encoding": "rgb8", "step": 12,
                                      "data": list(frame_data(shade))}, count=3, period=0.1)

            async def shown(shade: int = shade) -> bool:
                frame = await feeds.frame("front")
                return read_png(frame.data)[4] == frame_data(shade)

            await eventually(shown, timeout=20, what=f"frame {shade}")
        frame = await feeds.frame("front")
        assert (frame.mime, frame.width, frame.height) == ("image/png", 4, 3)
        jpeg = b"\xff\xd8\xff\xe0" + bytes(range(60))
        await oracle.acall("publish", topic="/cam/jpeg", type="sensor_msgs/msg/CompressedImage",
                           value={"format": "jpeg", "data": list(jpeg)}, count=3, period=0.1)

        async def passed_on() -> bool:
            try:
                return (await feeds.frame("jpeg")).data == jpeg
            except ImageUnavailable:
                return False

        await eventually(passed_on, timeout=20, what="the jpeg frame")
        with pytest.raises(ImageUnavailable) as unknown:
            await feeds.frame("rear")
        assert unknown.value.reason == "image_not_found"
    finally:
        feeds.close()


def robot_drawn_at(rows: bytes) -> tuple[float, float]:
    """The centre of the red square in an overhead frame."""
    found = [(i // 3 % WIDTH, i // 3 // WIDTH) for i in range(0, len(rows), 3)
             if tuple(rows[i:i + 3]) == ROBOT]
    assert found, "no robot in the frame"
    return (sum(u for u, _ in found) / len(found), sum(v for _, v in found) / len(found))


async def test_the_sims_overhead_camera_over_rest_and_mcp(sim: Demo, tmp_path: Path) -> None:
    async with aiohttp.ClientSession() as http:
        status = await wait_status(http, sim, lambda s: s["ros"]["connected"]
                                   and s["telemetry"]["position"] is not None)
        code, listed = await call(http, sim, sim.user, "GET", "/api/images")
        assert (code, listed) == (200, {"images": [{"name": "overhead",
                                                    "path": "/api/images/overhead"}]})
        headers = {"Authorization": f"Bearer {sim.user}"}

        async def frame() -> bytes | None:
            async with http.get(f"{sim.url}/api/images/overhead", headers=headers) as resp:
                return await resp.read() if resp.status == 200 else None

        png = await eventually(frame, timeout=20, what="the first overhead frame")
        width, height, _, _, rows = read_png(png)
        assert (width, height) == (WIDTH, HEIGHT)
        position = status["telemetry"]["position"]
        u, v = robot_drawn_at(rows)
        want = pixel_of(position["x"], position["y"])
        assert abs(u - want[0]) <= 1 and abs(v - want[1]) <= 1, ((u, v), want)
        async with http.get(f"{sim.url}/api/images/overhead") as resp:
            assert resp.status == 401
        async with http.get(f"{sim.url}/api/images/rear", headers=headers) as resp:
            assert (resp.status, (await resp.json())["reason"]) == (404, "image_not_found")
    for door in ("http", "stdio"):
        async with agent(sim, tmp_path, door=door) as client:
            uris = {str(r.uri) for r in (await client.list_resources()).resources}
            assert "robot://image/overhead" in uris, door
            contents = (await client.read_resource("robot://image/overhead")).contents[0]
            assert isinstance(contents, BlobResourceContents), door
            assert contents.mime_type == "image/png"
            assert read_png(base64.b64decode(contents.blob))[:2] == (WIDTH, HEIGHT)
