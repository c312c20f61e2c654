"""The configured camera topics (`bridge.ros2.images`): their newest frames, shown on request.

Frames are kept as they arrived (the CDR bytes of the newest sample, nothing decoded on the
reader thread: a camera at 30 Hz costs a copy per frame and no more) and turned into an image
file only when a client asks, on a thread of this module's own — never the default executor,
which the audit log's fsyncs use. A frame asked for twice is encoded once.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from ..api.ports import ImageFrame, ImageUnavailable
from ..config import ImageFeedConfig
from ..ros import qos
from ..ros.participant import RosNode
from ..ros.serialization import deserialize
from .png import UnsupportedImage, image_to_png

COMPRESSED = "sensor_msgs/msg/CompressedImage"
MIME = {"jpeg": "image/jpeg", "jpg": "image/jpeg", "png": "image/png"}


def compressed_mime(fmt: str) -> str | None:
    """CompressedImage.format ("jpeg", "png", "rgb8; jpeg compressed bgr8", ...) → MIME."""
    for word in reversed(fmt.replace(";", " ").lower().split()):
        if word in MIME:
            return MIME[word]
    return None


def encode(type_name: str, sample: bytes) -> tuple[str, bytes, int | None, int | None]:
    """(mime, file, width, height) of one sample (raises UnsupportedImage)."""
    try:
        msg: Any = deserialize(type_name, sample)
    except Exception as exc:  # a sample its own type cannot decode: nothing to show
        raise UnsupportedImage(f"a {type_name} that does not decode: {exc}") from None
    if type_name == COMPRESSED:
        mime = compressed_mime(str(msg.format))
        if mime is None:
            raise UnsupportedImage(f"compressed format {msg.format!r} (shown: jpeg, png)")
        return mime, bytes(msg.data), None, None
    png = image_to_png(str(msg.encoding), int(msg.width), int(msg.height), int(msg.step),
                       bytes(msg.data), bool(msg.is_bigendian))
    return "image/png", png, int(msg.width), int(msg.height)


class _Feed:
    def __init__(self, type_name: str) -> None:
        self.type_name = type_name
        self.sample: bytes | None = None
        self.arrived = 0.0
        self.shown: tuple[bytes, tuple[str, bytes, int | None, int | None]] | None = None


class ImageFeeds:
    """`api.ports.ImageSource` over DDS; `close` when the node goes."""

    def __init__(self, node: RosNode, images: Mapping[str, ImageFeedConfig], *,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self._monotonic = monotonic
        self._lock = threading.Lock()
        self._feeds = {name: _Feed(feed.type) for name, feed in images.items()}
        self._encoder = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="rcan-image")
        newest = qos.SENSOR_DATA.with_(depth=1)  # only the newest frame is ever shown
        self._subscriptions = [
            node.create_subscription(feed.topic, feed.type, newest, raw=True,
                                     callback=self._keeper(name))
            for name, feed in images.items()]

    def _keeper(self, name: str) -> Callable[[Any], None]:
        feed = self._feeds[name]

        def keep(sample: Any) -> None:  # the node's reader thread
            with self._lock:
                feed.sample, feed.arrived = bytes(sample), self._monotonic()

        return keep

    def names(self) -> list[str]:
        return sorted(self._feeds)

    async def frame(self, name: str) -> ImageFrame:
        feed = self._feeds.get(name)
        if feed is None:
            raise ImageUnavailable("image_not_found", f"no image named {name!r}")
        with self._lock:
            sample, arrived, shown = feed.sample, feed.arrived, feed.shown
        if sample is None:
            raise ImageUnavailable("no_frame_yet", f"{name}: no frame has arrived yet")
        if shown is not None and shown[0] is sample:
            encoded = shown[1]
        else:
            loop = asyncio.get_running_loop()
            try:
                encoded = await loop.run_in_executor(self._encoder, encode, feed.type_name,
                                                     sample)
            except UnsupportedImage as exc:
                raise ImageUnavailable("unsupported_image", f"{name}: {exc}") from None
            with self._lock:
                feed.shown = (sample, encoded)
        mime, data, width, height = encoded
        return ImageFrame(mime=mime, data=data, width=width, height=height,
                          age_s=round(self._monotonic() - arrived, 3))

    def close(self) -> None:
        for subscription in self._subscriptions:
            subscription.close()
        self._encoder.shutdown(wait=False, cancel_futures=True)
