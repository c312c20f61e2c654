"""RURI, in both generations' grammars (lowercase; optional `:port` and `/capability`):

    RCAN 2.1+   rcan://<registry>/<manufacturer>/<model>/<version>/<device-id>
    RCAN 1.2    rcan://<registry>/<manufacturer>/<model>/<device-id>

The 2.1+ form is what the official SDK's `RobotURI` parses and prints. The version segment looks
like a version (`v2`, `v1.3`, `1.0.0`: a `v` or a dot, so that an all-digit 1.2 device-id such
as `12345678` is never taken for one); the device-id is at least 8 characters in both forms.
A path that fits both forms (a 1.2 device-id that looks like a version, then a capability) is
read as 2.1+.

Two RURIs name the same robot (`Ruri.robot`) when registry, manufacturer, model and device-id
are equal, and the versions are too where both give one: a 1.2 client that leaves the version
out still reaches a robot configured with the 2.1+ form, and the other way round.
"""

from __future__ import annotations

import re

import msgspec

from ._errors import InvalidRuriError

_SEGMENT = r"[a-z0-9](?:[a-z0-9._-]*[a-z0-9])?"
_VERSION = r"v[0-9]+(?:\.[0-9]+)*|[0-9]+(?:\.[0-9]+)+"
_TAIL = rf"(?::(?P<port>[0-9]{{1,5}}))?(?:/(?P<capability>{_SEGMENT}))?"
_HEAD = rf"rcan://(?P<registry>{_SEGMENT})/(?P<manufacturer>{_SEGMENT})/(?P<model>{_SEGMENT})"
_RURI_21 = re.compile(rf"{_HEAD}/(?P<version>{_VERSION})/(?P<device_id>{_SEGMENT}){_TAIL}")
_RURI_12 = re.compile(rf"{_HEAD}/(?P<device_id>{_SEGMENT}){_TAIL}")
_MAX_LEN = 512
_MIN_DEVICE_ID = 8
GRAMMAR = ("rcan://registry/manufacturer/model/version/device-id (RCAN 2.1+) or "
           "rcan://registry/manufacturer/model/device-id (RCAN 1.2), each with optional "
           ":port and /capability")


class RobotId:
    """A robot's identity: a RURI without port and capability. Equal to another (or to a RURI
    string naming the same robot) as the module says: the version counts where both have one."""

    __slots__ = ("_key", "_text", "_version")

    def __init__(self, registry: str, manufacturer: str, model: str, device_id: str,
                 version: str | None) -> None:
        self._key = (registry, manufacturer, model, device_id)
        self._version = version
        middle = f"{model}/{version}" if version else model
        self._text = f"rcan://{registry}/{manufacturer}/{middle}/{device_id}"

    def __str__(self) -> str:
        return self._text

    def __repr__(self) -> str:
        return f"RobotId({self._text!r})"

    def __eq__(self, other: object) -> bool:
        if isinstance(other, str):
            try:
                other = parse_ruri(other).robot
            except InvalidRuriError:
                return False
        if not isinstance(other, RobotId):
            return NotImplemented
        if self._key != other._key:
            return False
        return self._version is None or other._version is None or self._version == other._version

    def __hash__(self) -> int:
        return hash(self._key)  # the version may be left out on one side: not part of the hash


class Ruri(msgspec.Struct, frozen=True):
    registry: str
    manufacturer: str
    model: str
    device_id: str
    port: int | None = None
    capability: str | None = None
    version: str | None = None  # the 2.1+ form's version segment

    def __str__(self) -> str:
        port = f":{self.port}" if self.port is not None else ""
        cap = f"/{self.capability}" if self.capability else ""
        return f"{self.robot}{port}{cap}"

    @property
    def robot(self) -> RobotId:
        """The robot's identity without port and capability."""
        return RobotId(self.registry, self.manufacturer, self.model, self.device_id,
                       self.version)


def parse_ruri(text: str) -> Ruri:
    """Parse and validate a RURI of either grammar; anything else raises InvalidRuriError."""
    if not isinstance(text, str):
        raise InvalidRuriError(repr(text), "not a string")
    if len(text) > _MAX_LEN:
        raise InvalidRuriError(text[:40] + "…", f"longer than {_MAX_LEN} characters")
    if text != text.lower():
        raise InvalidRuriError(text, "must be lowercase")
    match = _RURI_21.fullmatch(text)
    if match is None or len(match["device_id"]) < _MIN_DEVICE_ID:
        match = _RURI_12.fullmatch(text)
    if match is None:
        raise InvalidRuriError(text, f"expected {GRAMMAR}")
    if len(match["device_id"]) < _MIN_DEVICE_ID:
        raise InvalidRuriError(text, f"device-id must be at least {_MIN_DEVICE_ID} characters")
    port = int(match["port"]) if match["port"] else None
    if port is not None and not 1 <= port <= 65535:
        raise InvalidRuriError(text, "port out of range 1..65535")
    groups = match.groupdict()
    return Ruri(
        registry=match["registry"],
        manufacturer=match["manufacturer"],
        model=match["model"],
        device_id=match["device_id"],
        port=port,
        capability=match["capability"],
        version=groups.get("version"),
    )
