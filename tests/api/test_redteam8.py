"""Red team 8: what an authenticated principal controls in a body, and what it can do to others.

Each test here failed on main (43f1bcd) before its fix; see each test's docstring.
"""

from __future__ import annotations

from typing import Any

from tests.api.apihelpers import Api
from tests.api.test_rcan3_messages import sdk_command

SMALL_WINDOW = "security: {msg_id_cache_size: 100}"


async def test_a_guest_cannot_fill_the_replay_window_for_everyone(tmp_path: Any) -> None:
    """A GUEST (or any principal, rate-limited or not) sending fresh RCAN 3.x messages it may
    not even run filled the one §8.3 id window: from then on every principal's fresh message
    was refused 429 `replay_window_full` until the GUEST's ids went stale — a denial of
    service of every RCAN 3.x client by the least trusted one. A full window is the flooder's
    problem only."""
    api = await Api(tmp_path, bridge_extra=SMALL_WINDOW).start()
    try:
        for _ in range(100):
            status, body = await api.command("viewer", sdk_command(api, "move",
                                                                   {"linear_x": 0.1}))
            assert status == 403, body  # a GUEST may not move: refused, but its id was kept
        status, body = await api.command("viewer", sdk_command(api, "move", {"linear_x": 0.1}))
        assert (status, body.get("reason")) == (429, "replay_window_full"), body
        msg = sdk_command(api, "move", {"linear_x": 0.2, "duration_s": 1.0})
        status, body = await api.command("planner", msg)
        assert (status, body["outcome"]) == (200, "executed"), body
        status, body = await api.command("planner", msg)  # and replays are still caught
        assert (status, body["error_code"]) == (409, "REPLAY_DETECTED"), body
    finally:
        await api.close()
