"""GET /api/images and /api/images/{name} over a camera source kept in memory: any principal
reads a frame (a file, never cached); what cannot be shown is refused with its reason; the
same frames as MCP resources at /mcp."""

from __future__ import annotations

import base64
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from mcp.shared.exceptions import MCPError
from mcp_types import BlobResourceContents

from rcan_rtps.api.ports import ImageFrame, ImageUnavailable
from tests.api.apihelpers import Api, auth
from tests.api.test_mcp_http import agent

PNG = b"\x89PNG\r\n\x1a\n-a-frame"


class Cameras:
    """An ImageSource: `front` has a frame, `rear` none yet, `ir` an unsupported one."""

    def names(self) -> list[str]:
        return ["front", "ir", "rear"]

    async def frame(self, name: str) -> ImageFrame:
        if name == "front":
            return ImageFrame(mime="image/png", data=PNG, width=4, height=3, age_s=0.25)
        if name == "rear":
            raise ImageUnavailable("no_frame_yet", "rear: no frame has arrived yet")
        if name == "ir":
            raise ImageUnavailable("unsupported_image", "ir: encoding 'yuv422'")
        raise ImageUnavailable("image_not_found", f"no image named {name!r}")


@pytest.fixture
async def cams(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, images=Cameras()).start()
    yield harness
    await harness.close()


async def test_frames_for_any_principal_and_refusals_by_reason(cams: Api) -> None:
    status, listed = await cams.call("GET", "/api/images", "viewer")
    assert (status, [i["name"] for i in listed["images"]]) == (200, ["front", "ir", "rear"])
    async with cams.http.get("/api/images/front", headers=auth("viewer")) as resp:
        assert (resp.status, resp.content_type, await resp.read()) == (200, "image/png", PNG)
        assert resp.headers["Cache-Control"] == "no-store"
        assert (resp.headers["X-Image-Size"], resp.headers["X-Image-Age-S"]) == ("4x3", "0.25")
    for name, status_code, reason in (("rear", 503, "no_frame_yet"),
                                      ("ir", 422, "unsupported_image"),
                                      ("nope", 404, "image_not_found")):
        status, body = await cams.call("GET", f"/api/images/{name}", "planner")
        assert (status, body["reason"]) == (status_code, reason), name
    status, _ = await cams.call("GET", "/api/images/front")
    assert status == 401


async def test_frames_as_mcp_resources(cams: Api) -> None:
    async with agent(cams) as client:
        resources = {str(r.uri) for r in (await client.list_resources()).resources}
        assert {"robot://image/front", "robot://image/rear"} <= resources
        templates = (await client.list_resource_templates()).resource_templates
        assert [t.uri_template for t in templates] == ["robot://image/{name}"]
        got = (await client.read_resource("robot://image/front")).contents[0]
        assert isinstance(got, BlobResourceContents) and base64.b64decode(got.blob) == PNG
        with pytest.raises(MCPError, match="no_frame_yet"):
            await client.read_resource("robot://image/rear")
        with pytest.raises(MCPError, match="image_not_found"):
            await client.read_resource("robot://image/nope")
