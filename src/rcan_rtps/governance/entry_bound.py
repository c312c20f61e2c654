"""The bound on what a request puts in its audit entry (red team 26 follow-up).

An entry records a command's params as requested — refused ones and stops too, and a stop's
body is read up to 4x `api.max_body_bytes` — in RCAN canonical JSON v1, which writes a whole
float as an integer: `1e300`, 5 bytes sent, is 301 digits logged. A GUEST's stop of 256 KiB
made an entry of 13 MB; at the 16 MiB body limit, one entry could reach 3 GB (the disk, and
every reader of the log, held it). The canonical form stays (the SDK recomputes every id): what
a request may put in one entry is bounded instead, here, in one place.

The request content of an entry — its `params` (for the events that record a command's params
as requested), the names in `rcan.ignored`, the `warnings` — is held to `limit` bytes of
canonical JSON together, in that order; a field that does not fit in what is left is replaced by
a marker that says what was sent without repeating it: `{"omitted": "too_large_to_log",
"json_bytes": N, "sha256": <hex>, "limit_bytes": L}`, where N and the digest are of the
compact JSON the bridge decoded (msgspec's: keys in the order received, floats in their
shortest round-trip form, so never amplified). The entry's own `omitted` field lists the fields
so replaced (`["params"]`, `"rcan.ignored"`, `"warnings"`): a request's params may look like
a marker, and are then logged as sent, unlisted.

`request_bytes_limit` derives the limit from the body limit so that an executed command's params
are always logged whole: the only growth canonical JSON gives an accepted command's params is
a number's spelling — every number a command is accepted with is at most 1e9 in size
(`rcan._types.Finite`), and `1e9,` (4 bytes sent) is `1000000000,` (11 logged), 2.75 times; a
string, a key, an integer or a non-whole float is never longer logged than sent by more than
that (`1e-7` → `1e-07`). So the params of a body within `max_body_bytes` take at most 2.75 times
it, under 3 times it. A command whose params would not be logged whole all the same (an
INVOKE's skill whose fixed params the config made that large) is refused before it runs
(`Governor`, PAYLOAD_TOO_LARGE `params_too_large_to_log`), never executed with a marker; a stop
always stops, and its entry carries the marker.

The size is measured by a walk that stops once past the limit, before anything is encoded: the
canonical size exactly (each number's digits counted one number at a time), so params are kept
whenever their canonical JSON fits, and the amplified form is never made to be measured.
"""

from __future__ import annotations

import hashlib
import math
from typing import Any

import msgspec

# The least the bound is, whatever the body limit: small bodies' refusals are logged whole.
FLOOR_BYTES = 64 * 1024
# The canonical JSON of an accepted command's params is at most 2.75 times its body's size.
GROWTH = 3
OMITTED = "too_large_to_log"
# The entry field that lists which of its request fields the bridge replaced by a marker.
OMITTED_FIELDS = "omitted"


def request_bytes_limit(max_body_bytes: int) -> int:
    """The bound on a request's content in one entry, for a body limit of `max_body_bytes`."""
    return max(FLOOR_BYTES, GROWTH * max_body_bytes)


def size_within(value: Any, budget: int) -> int | None:
    """`value`'s size in RCAN canonical JSON v1, or None once that passes `budget` (the walk
    stops there: no more of `value` is looked at, nothing of it is encoded whole)."""
    total = 0
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            total += 1 + 2 * len(item) if item else 2  # braces, a colon each, commas between
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            total += 1 + len(item) if item else 2  # brackets, commas between
            stack.extend(item)
        else:
            total += _scalar_size(item)
        if total > budget:
            return None
    return total


def canonical_float(value: float) -> int | float | None:
    """How RCAN canonical JSON v1 writes a float: null if it is not finite (a stop's `1e400`,
    read as infinity), the integer if it is whole (50.0 → 50, 1e300 → 301 digits), else
    itself (its repr). The log's encoder (`audit`) and the size walk here both ask this."""
    if not math.isfinite(value):
        return None
    return int(value) if value.is_integer() else value


def _scalar_size(item: Any) -> int:
    if item is None or item is True:
        return 4
    if item is False:
        return 5
    if isinstance(item, float):  # the digits of one number, never the whole
        written = canonical_float(item)
        return 4 if written is None else len(repr(written))
    if isinstance(item, int):
        if item.bit_length() > 10_000:  # (str() refuses so many digits: counted instead)
            return item.bit_length() * 30103 // 100_000 + 2
        return len(str(item))
    return len(msgspec.json.encode(item))  # a string: escaped as canonical JSON escapes it


def omitted(value: Any, limit: int) -> dict[str, Any]:
    """The marker that stands for `value` (too large to log): its compact JSON's size and
    SHA-256, and the limit it passed."""
    compact = msgspec.json.encode(value)
    return {"omitted": OMITTED, "json_bytes": len(compact),
            "sha256": hashlib.sha256(compact).hexdigest(), "limit_bytes": limit}


def bound_request_content(entry: dict[str, Any], limit: int, *, params: bool) -> None:
    """Holds `entry`'s request content to `limit` bytes together (in place): `params` (when
    `params`: the entry records a command's params as requested), then `rcan.ignored`, then
    `warnings`; each that does not fit in what is left becomes its marker, and the entry's
    `omitted` lists the fields so replaced. Only that list tells a marker from a client's
    params that look like one (a request may send `{"omitted": "too_large_to_log", ...}`
    itself: it is logged as sent, and not listed)."""
    left = limit
    replaced: list[str] = []
    if params and entry.get("params") is not None:
        left = _fitted(entry, "params", left, limit, replaced)
    rcan = entry.get("rcan")
    if isinstance(rcan, dict) and rcan.get("ignored"):
        entry["rcan"] = rcan = dict(rcan)  # (the caller's own dict is left as it was)
        left = _fitted(rcan, "ignored", left, limit, replaced, "rcan.ignored")
    if entry.get("warnings"):
        _fitted(entry, "warnings", left, limit, replaced)
    if replaced:
        entry[OMITTED_FIELDS] = replaced


def _fitted(holder: dict[str, Any], key: str, left: int, limit: int, replaced: list[str],
            name: str | None = None) -> int:
    """`holder[key]` kept if it fits in `left` bytes, else its marker (and `name`, the
    field's name in the entry, noted in `replaced`); what is left then."""
    size = size_within(holder[key], left)
    if size is not None:
        return left - size
    replaced.append(name or key)
    if key == "warnings":  # a list of text stays one: its marker is the one line
        marker = omitted(holder[key], limit)
        holder[key] = [f"{len(holder[key])} warnings {OMITTED}: {marker['json_bytes']} bytes "
                       f"of JSON, sha256 {marker['sha256']}"]
    else:
        holder[key] = omitted(holder[key], limit)
    return left  # (a marker is of a fixed size: not counted against the request's bytes)
