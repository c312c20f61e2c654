"""The largest sample a domain of this process sends, and the error of a write past it.

A domain's first node sets it (`RosNode(max_sample_bytes=)`, Cyclone's
`<Internal><MaxSampleSize>`); the user's CYCLONEDDS_URI comes after ours and may set another.
Cyclone refuses a write past it with a warning on stderr and a bare DDS_RETCODE_ERROR, the
code it also gives for a writer being deleted: the size against the bound tells the two apart,
and the write fails only when a reader of the sample is in this process — with readers
elsewhere only, Cyclone drops it with its warning and returns as if it had sent it. So every
writer of ours (topics, service requests and replies, ros_discovery_info: `RosNode.write_cdr`)
checks a sample against our bound before writing it, and says SampleTooLarge. Where
CYCLONEDDS_URI names MaxSampleSize (inline, or in a file it names) the bound in force is its
own, not read here: nothing is checked before, and a refusal is said to be most likely past
it.
"""

from __future__ import annotations

from pathlib import Path

import msgspec
from cyclonedds.core import DDSException

from .errors import SampleTooLarge

UNCHECKED = (1 << 31) - 1  # Cyclone checks no size at or past this (its default)
_FILE_READ_LIMIT = 1 << 20  # a configuration file larger than this is not looked into


class SampleBound(msgspec.Struct, frozen=True):
    """Ours (`size`), and whether the user's CYCLONEDDS_URI may set another."""

    size: int
    user_sets: bool = False


def bound_in_force(ours: int, user_uri: str) -> SampleBound:
    """Ours, and whether `user_uri` (CYCLONEDDS_URI: inline XML and file names, comma
    separated) mentions MaxSampleSize anywhere — in its text, or in a file it names (one that
    cannot be read here counts). A token is taken for a file when it looks like one (`file://`,
    a `/`, `.xml`): inline XML may hold commas too."""
    files = [token for token in (t.strip() for t in user_uri.split(","))
             if token.startswith("file://") or ("/" in token and "<" not in token)
             or token.endswith(".xml")]
    texts = [user_uri, *(_read(path) for path in files)]
    return SampleBound(ours, any("maxsamplesize" in text.lower() for text in texts))


def _read(token: str) -> str:
    path = token.removeprefix("file://")
    try:
        with Path(path).open(encoding="utf-8", errors="replace") as file:
            return file.read(_FILE_READ_LIMIT)
    except OSError:
        return "MaxSampleSize?"  # not readable here: it may set one


def past_bound(length: int, bound: SampleBound | None, what: str,
               domain_id: int) -> SampleTooLarge | None:
    """SampleTooLarge when `length` bytes of CDR (with header) are past our bound, to be
    raised before the write; None otherwise, or when CYCLONEDDS_URI sets the bound (its value
    is Cyclone's alone)."""
    if bound is None or bound.user_sets or bound.size >= UNCHECKED:
        return None
    size = length + (-length & 3)  # Cyclone's size of a sample: padded to whole words
    if size <= bound.size:
        return None
    return SampleTooLarge(f"{what} of {length} bytes is past the largest sample this process "
                          f"sends on domain {domain_id} ({bound.size} bytes: max_sample_bytes)")


def refused_for_size(exc: DDSException, length: int, bound: SampleBound | None,
                     what: str, domain_id: int) -> SampleTooLarge | None:
    """SampleTooLarge when `exc`, from writing `length` bytes, is most likely Cyclone refusing
    a sample past the MaxSampleSize CYCLONEDDS_URI sets (a DDS_RETCODE_ERROR, which a writer
    being deleted gives too); None when it is something else."""
    if exc.code != DDSException.DDS_RETCODE_ERROR or bound is None or not bound.user_sets:
        return None
    return SampleTooLarge(f"{what} of {length} bytes was not sent: Cyclone refused it on "
                          f"domain {domain_id}, most likely as past the MaxSampleSize "
                          "CYCLONEDDS_URI sets (past it, a sample read only by other "
                          "processes is dropped with Cyclone's warning alone)")
