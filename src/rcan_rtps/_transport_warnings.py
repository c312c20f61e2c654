"""The `RCAN-Transport-Warnings` header of `POST /api/command`: what a client's own transport
found wrong with a stop before it became this request, for the stop's audit entry.

`rcan-rtps mcp` is a REST client of the bridge: a stop its stdio door read from a malformed
line (`mcp_server.stdio_door`) reaches the bridge as a well-formed command, and its warnings
would reach the agent and stderr but not the audit entry, unlike those of the bridge's own
`/mcp`. The header carries them: a JSON array of strings. Both ends share this module (no
import of the API or the MCP server: both load it).

The bridge records them only for a stop (any other command's header is ignored), each marked
as the client's (`client: `: the bridge cannot check what a client says of its transport),
with non-printable characters escaped, at most `MAX_COUNT` of at most `MAX_CHARS` characters
each. A header that cannot be read that way is one warning saying so: it never keeps a stop
from stopping. The client keeps its header under `MAX_HEADER_BYTES`, well below the HTTP
parser's limit on a header field (8190 bytes; over it, any request is refused 431).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence

import msgspec

HEADER = "RCAN-Transport-Warnings"
MARK = "client: "
MAX_COUNT = 8
MAX_CHARS = 500
MAX_HEADER_BYTES = 4096
_NOT_READ = f"{HEADER}: not a JSON array of strings: ignored"


def bounded(warning: str) -> str:
    """`warning` as the header carries it: non-printable characters (line breaks, controls,
    unpaired surrogates) as Python escapes, at most `MAX_CHARS` characters (a cut one ends
    with `…`). Applying it twice changes nothing."""
    text = "".join(c if c.isprintable() else ascii(c)[1:-1] for c in warning[:MAX_CHARS * 2])
    return text if len(text) <= MAX_CHARS else text[:MAX_CHARS - 1] + "…"


def header_value(warnings: Iterable[str]) -> str | None:
    """The header for `warnings` (ASCII), as many of them as fit in `MAX_HEADER_BYTES`; None
    when none are given."""
    items: list[str] = []
    size = 2  # the brackets
    for warning in list(warnings)[:MAX_COUNT]:
        item = _fitted(bounded(warning), MAX_HEADER_BYTES - size - 1)
        if item is None:
            break
        items.append(item)
        size += len(item) + 1
    return "[" + ",".join(items) + "]" if items else None


def _fitted(text: str, room: int) -> str | None:
    """`text` as a JSON string of at most `room` bytes, cut (ending with `…`) as much as it
    must be (a character may take 12 bytes escaped); None when not even `…` fits."""
    item = json.dumps(text, ensure_ascii=True)
    keep = len(text)
    while len(item) > room:
        keep //= 2
        if keep == 0:
            return None
        item = json.dumps(text[:keep - 1] + "…", ensure_ascii=True)
    return item


def recorded(values: Sequence[str]) -> tuple[str, ...]:
    """The header's values (as many as were sent) as a stop's audit entry records them."""
    if not values:
        return ()
    if len(values) > 1:
        return (f"{HEADER}: sent {len(values)} times: ignored",)
    try:
        # surrogateescape: the bytes as they came (aiohttp's reading of a header).
        said = msgspec.json.decode(values[0].encode("utf-8", "surrogateescape"),
                                   type=list[str])
    except (msgspec.DecodeError, ValueError, RecursionError):  # ValueError: not UTF-8
        return (_NOT_READ,)
    kept = [MARK + bounded(w) for w in said[:MAX_COUNT] if w]
    if len(said) > MAX_COUNT:
        kept.append(f"{HEADER}: {len(said) - MAX_COUNT} more warnings not recorded "
                    f"(at most {MAX_COUNT})")
    return tuple(kept)


def unrecorded(sent: Iterable[str], answered: Iterable[str]) -> list[str]:
    """Those of the warnings `sent` that the bridge's reply (its `warnings`, `answered`) does
    not carry as recorded: a bridge that predates the header, or one over the bounds."""
    have = set(answered)
    return [w for w in sent if MARK + bounded(w) not in have]
