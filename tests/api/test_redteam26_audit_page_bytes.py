"""Red team 26: a page of GET /api/audit is held to a byte budget, not only to 1,000 entries.

An entry records a command's params as requested, refused ones too, and a stop's body is taken
up to 4x `max_body_bytes` (a stop always stops). Canonical JSON writes a whole float as an
integer, so `1e300` (5 bytes sent) is 301 digits in the log: a GUEST's refused stop of 256 KiB
is an entry of about 13 MB, and a page of 1,000 of them ran to gigabytes (more still with
`max_body_bytes` at its 16 MiB maximum). A page now stops before its entries pass
`_reads.PAGE_BYTES` together; an entry larger than that alone is a page by itself, and a
client paging on by `next_since` gets every entry once.

(What a request puts in an entry is now held to 3x `max_body_bytes` too,
`governance.entry_bound`: the body limit is raised here so that entries larger than a page are
still made.)"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from rcan_rtps.api._reads import PAGE_BYTES
from tests.api.apihelpers import Api, auth

MAX_BODY = 2 << 20  # entries of up to 6 MiB of request content are logged whole
WRAPPER = 200  # a page's bytes besides its entries: {"entries":[...],"next_since":…}


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    api = await Api(tmp_path, max_body=MAX_BODY).start()
    yield api
    await api.close()


def _stop_of_big_params() -> bytes:
    """A stop body whose params are thousands of `1e300`: 5 MiB logged (302 bytes each)."""
    count = (5 << 20) // 302
    return b'{"action":"stop","params":{"x":[' + b",".join([b"1e300"] * count) + b"]}}"


async def _page(api: Api, path: str, who: str) -> tuple[int, dict[str, Any]]:
    async with api.http.get(path, headers=auth(who)) as resp:
        assert resp.status == 200, await resp.text()
        body = await resp.read()
    return len(body), json.loads(body)


async def test_audit_pages_are_held_to_their_byte_budget(api: Api) -> None:
    for big in (False, True, False, False, True, False):
        raw = _stop_of_big_params() if big else b'{"action":"stop","params":{"x":[1]}}'
        status, body = await api.command("viewer", raw=raw)  # a GUEST may not stop: refused
        assert (status, body["error_code"]) == (403, "INSUFFICIENT_PRIVILEGES"), body
    lines = (api.tmp / "audit.jsonl").read_bytes().splitlines()
    assert max(map(len, lines)) > PAGE_BYTES  # an entry of ~5 MB from a body of 100 kB
    assert sum(map(len, lines)) > 2 * PAGE_BYTES

    seqs: list[int] = []
    since, pages = 0, 0
    while True:
        size, page = await _page(api, f"/api/audit?since={since}", "ops")
        if not page["entries"]:
            break
        pages += 1
        assert len(page["entries"]) == 1 or size <= PAGE_BYTES + WRAPPER, (size, pages)
        seqs += [e["seq"] for e in page["entries"]]
        since = page["next_since"]
    assert seqs == list(range(1, len(lines) + 1))  # every entry, once, in order
    assert pages >= 3  # the large entries each came on a page alone

    # The caller's own newest entries: those after its last large one fit; that one does not.
    size, mine = await _page(api, "/api/audit/mine?last=1000", "viewer")
    assert size <= PAGE_BYTES + WRAPPER
    assert [e["seq"] for e in mine["entries"]] == [len(lines)]
