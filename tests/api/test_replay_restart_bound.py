"""A restart after a window denser than the replay window's bound: the start keeps the
newest ids of each principal, as a run does, and refuses a replay of one it did not keep."""

from __future__ import annotations

from pathlib import Path

from tests.api.apihelpers import Api
from tests.api.test_rcan3_messages import sdk_command
from tests.api.test_redteam8 import SMALL_WINDOW

MOVE = {"linear_x": 0.1, "duration_s": 1.0}


async def _restarted(api: Api, after_s: float) -> Api:
    """The bridge, of the same config, stopped and started again on the same audit log
    `after_s` later (its e-stop, latched by the motion the first run left, cleared)."""
    then = api.clock.time()
    await api.close()
    again = Api(api.tmp, bridge_extra=SMALL_WINDOW)
    again.clock.advance(then + after_s - again.clock.time())
    await again.start()
    status, _ = await again.command("ops", {"action": "clear_estop"})
    assert status == 200
    return again


async def test_a_replay_of_an_id_the_start_did_not_keep_is_refused(tmp_path: Path) -> None:
    api = await Api(tmp_path, bridge_extra=SMALL_WINDOW).start()  # 100 ids a principal
    first = sdk_command(api, "move", MOVE)
    assert (await api.command("planner", first))[0] == 200
    for _ in range(99):
        assert (await api.command("planner", sdk_command(api, "move", MOVE)))[0] == 200
    status, body = await api.command("planner", sdk_command(api, "move", MOVE))
    assert (status, body.get("reason")) == (429, "replay_window_full"), body  # its id logged
    again = await _restarted(api, after_s=6)  # 101 of the planner's ids in the log's window
    try:
        moves = len(again.dispatcher.calls)
        status, body = await again.command("planner", first)
        assert (status, body["error_code"], body.get("reason")) == (
            408, "MESSAGE_STALE", "older_than_the_ids_kept_at_start"), body
        assert len(again.dispatcher.calls) == moves  # not moved on the replay
        assert again.entry(body["audit_id"])["deny_reason"] == (
            "MESSAGE_STALE:older_than_the_ids_kept_at_start")
        # Another principal is not held up by the planner's flood.
        status, body = await again.command("ops", sdk_command(again, "move", MOVE))
        assert (status, body["outcome"]) == (200, "executed"), body
    finally:
        await again.close()
