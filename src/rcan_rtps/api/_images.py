"""GET /api/images and /api/images/{name}: the configured cameras' newest frames (any
authenticated principal, like STATUS). A raw frame is a PNG, a compressed one is passed on as
it came; the size and the frame's age are in headers. Never cached: a frame is a moment."""

from __future__ import annotations

from typing import Any

import msgspec

from .ports import ImageFrame, ImageUnavailable

# ImageUnavailable.reason → (HTTP status, error_code)
REFUSALS = {"image_not_found": (404, "NOT_FOUND"), "no_frame_yet": (503, "ROBOT_UNAVAILABLE"),
            "unsupported_image": (422, "UNSUPPORTED_IMAGE")}


class ImageEntry(msgspec.Struct, kw_only=True):
    name: str
    path: str


class ImageList(msgspec.Struct, kw_only=True):
    images: list[ImageEntry]


class _NoImages:
    """The source of a bridge without cameras."""

    def names(self) -> list[str]:
        return []

    async def frame(self, name: str) -> ImageFrame:
        raise ImageUnavailable("image_not_found", f"no image named {name!r}")


NO_IMAGES = _NoImages()


def image_list(names: list[str]) -> ImageList:
    return ImageList(images=[ImageEntry(name=n, path=f"/api/images/{n}") for n in names])


def frame_headers(frame: ImageFrame) -> dict[str, Any]:
    headers = {"Cache-Control": "no-store", "X-Image-Age-S": f"{frame.age_s:g}"}
    if frame.width is not None and frame.height is not None:
        headers["X-Image-Size"] = f"{frame.width}x{frame.height}"
    return headers
