"""RURI: `rcan://<registry>/<manufacturer>/<model>/<device-id>[:port][/capability]`."""

from __future__ import annotations

import re

import msgspec

from ._errors import InvalidRuriError

_SEGMENT = r"[a-z0-9](?:[a-z0-9._-]*[a-z0-9])?"
_RURI = re.compile(
    rf"rcan://(?P<registry>{_SEGMENT})/(?P<manufacturer>{_SEGMENT})/(?P<model>{_SEGMENT})"
    rf"/(?P<device_id>{_SEGMENT})(?::(?P<port>[0-9]{{1,5}}))?(?:/(?P<capability>{_SEGMENT}))?"
)
_MAX_LEN = 512


class Ruri(msgspec.Struct, frozen=True):
    registry: str
    manufacturer: str
    model: str
    device_id: str
    port: int | None = None
    capability: str | None = None

    def __str__(self) -> str:
        port = f":{self.port}" if self.port is not None else ""
        cap = f"/{self.capability}" if self.capability else ""
        base = f"rcan://{self.registry}/{self.manufacturer}/{self.model}/{self.device_id}"
        return f"{base}{port}{cap}"

    @property
    def robot(self) -> str:
        """The robot's identity without port and capability."""
        return f"rcan://{self.registry}/{self.manufacturer}/{self.model}/{self.device_id}"


def parse_ruri(text: str) -> Ruri:
    """Parse and validate a RURI; anything off-grammar raises InvalidRuriError."""
    if not isinstance(text, str):
        raise InvalidRuriError(repr(text), "not a string")
    if len(text) > _MAX_LEN:
        raise InvalidRuriError(text[:40] + "…", f"longer than {_MAX_LEN} characters")
    if text != text.lower():
        raise InvalidRuriError(text, "must be lowercase")
    match = _RURI.fullmatch(text)
    if match is None:
        raise InvalidRuriError(
            text, "expected rcan://registry/manufacturer/model/device-id[:port][/capability]"
        )
    if len(match["device_id"]) < 8:
        raise InvalidRuriError(text, "device-id must be at least 8 characters")
    port = int(match["port"]) if match["port"] else None
    if port is not None and not 1 <= port <= 65535:
        raise InvalidRuriError(text, "port out of range 1..65535")
    return Ruri(
        registry=match["registry"],
        manufacturer=match["manufacturer"],
        model=match["model"],
        device_id=match["device_id"],
        port=port,
        capability=match["capability"],
    )
