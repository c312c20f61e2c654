"""The largest sample a domain of this process takes in or sends, and the error of a write
past it.

A domain's first node sets it (`RosNode(max_sample_bytes=)`, Cyclone's
`<Internal><MaxSampleSize>`); the user's CYCLONEDDS_URI comes after ours and may set another,
which is then the bound Cyclone applies. Cyclone refuses a write past it with a warning on
stderr and a bare DDS_RETCODE_ERROR, the code it also gives for a writer being deleted: the
size and the bound in force tell the two apart, so every writer of ours (topics, service
requests and replies, ros_discovery_info) says SampleTooLarge with the bound and where it
was set, not "Non specific error".
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from cyclonedds.core import DDSException

from .errors import SampleTooLarge

# Cyclone's memsize units (ddsi_config.c); the number alone is bytes.
_UNITS = {"b": 1, "kib": 1 << 10, "kb": 1 << 10, "mib": 1 << 20, "mb": 1 << 20,
          "gib": 1 << 30, "gb": 1 << 30}
_ELEMENT = re.compile(r"<\s*MaxSampleSize\s*>([^<]*)<", re.IGNORECASE)
_VALUE = re.compile(r"\s*(\d+)\s*([A-Za-z]*)\s*")
_FILE_READ_LIMIT = 1 << 20  # a configuration file larger than this is not looked into
UNCHECKED = (1 << 31) - 1  # Cyclone checks no size at or past this (its default)


@dataclass(frozen=True)
class SampleBound:
    """The bound in force on a domain: `size` in bytes, or None when CYCLONEDDS_URI sets one
    whose value could not be read here (a file not readable, `${VAR}`); `source` says who
    set it."""

    size: int | None
    source: str


def bound_in_force(ours: int, user_uri: str) -> SampleBound:
    """The bound Cyclone applies when our fragment sets `ours` and the user's CYCLONEDDS_URI
    (after it) is `user_uri`: the last MaxSampleSize of that URI's inline XML and files wins,
    whatever its domain id (a bound set for another domain only is taken as this one's)."""
    found = _user_settings(user_uri)
    if not found:
        return SampleBound(ours, "max_sample_bytes")
    return SampleBound(_parse_memsize(found[-1]), "CYCLONEDDS_URI's MaxSampleSize")


def _user_settings(user_uri: str) -> list[str]:
    """Every MaxSampleSize value in the URI, in order: inline XML, and the files it names
    (a token that does not start with '<', up to the next comma, as Cyclone reads it)."""
    values: list[str] = []
    pos = 0
    while pos < len(user_uri):
        rest = user_uri[pos:].lstrip(" \t\r\n,")
        pos = len(user_uri) - len(rest)
        if not rest:
            break
        if rest.startswith("<"):  # inline XML, up to the next token that is a file
            end = _inline_end(user_uri, pos)
            values += _ELEMENT.findall(user_uri[pos:end])
        else:
            end = user_uri.find(",", pos)
            end = len(user_uri) if end < 0 else end
            values += _ELEMENT.findall(_read_config_file(user_uri[pos:end].strip()))
        pos = end
    return values


def _inline_end(uri: str, start: int) -> int:
    """Where the inline XML that starts at `start` ends: at a comma followed by a token that
    is not XML, else at the end."""
    for match in re.finditer(r",\s*(?=[^<\s,])", uri[start:]):
        return start + match.start()
    return len(uri)


def _read_config_file(token: str) -> str:
    for path in (token, token[7:] if token.startswith("file://") else None):
        if path is None:
            continue
        try:
            with Path(path).open("r", encoding="utf-8", errors="replace") as file:
                return file.read(_FILE_READ_LIMIT)
        except OSError:
            continue
    return "<MaxSampleSize>?<"  # not readable here: a bound may be set, its value unknown


def _parse_memsize(text: str) -> int | None:
    match = _VALUE.fullmatch(text)
    if match is None:
        return None
    unit = _UNITS.get((match.group(2) or "B").lower())
    return None if unit is None else int(match.group(1)) * unit


def refused_for_size(exc: DDSException, length: int, bound: SampleBound | None,
                     what: str, domain_id: int) -> SampleTooLarge | None:
    """SampleTooLarge when `exc`, from writing `length` bytes of CDR (with header), is
    Cyclone refusing a sample past `bound`; None when it is something else."""
    if exc.code != DDSException.DDS_RETCODE_ERROR or bound is None:
        return None
    size = length + (-length & 3)  # Cyclone's size of a sample: padded to whole words
    if bound.size is None:  # set by the user, to a value not read here: the likely cause
        return SampleTooLarge(f"{what} of {length} bytes was not sent: Cyclone refused it on "
                              f"domain {domain_id}, most likely as past {bound.source}")
    if bound.size >= UNCHECKED or size <= bound.size:
        return None
    return SampleTooLarge(f"{what} of {length} bytes is past the largest sample this process "
                          f"sends on domain {domain_id} ({bound.size} bytes: {bound.source})")
