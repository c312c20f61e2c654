"""A retried command (the 1.2 forms' idempotent retry) is not run twice across a restart.

Red team 20: the idempotency store lives in memory, so a move sent with a client's
`message_id`, and sent again after the bridge restarted (within the 10 minutes a retry is
promised its first outcome), was executed a second time — the robot moved twice. The first
outcome is now the log's: the retry is refused 409 MESSAGE_ID_CONFLICT
(`decided_before_restart`), audited, and nothing moves. A stop always runs again.
"""

from __future__ import annotations

from pathlib import Path

from tests.api.apihelpers import Api
from tests.api.test_redteam20 import _restarted

MOVE = {"action": "move", "message_id": "7d3f5a52-5e0b-4c39-9d61-2f6a4f0f0a11",
        "params": {"linear_x": 0.2, "duration_s": 1.0}}


async def _started_again(api: Api, after_s: float) -> Api:
    """`_restarted`, with the governor started as a run starts it (BRIDGE_STARTED: what the
    start reads back of the log comes first)."""
    again = await _restarted(api, after_s)
    await again.gov.start()
    return again


async def _closed(api: Api) -> None:
    await api.gov.stop()
    await api.close()


def _moves(api: Api) -> int:
    return sum(action == "move" for action, _ in api.dispatcher.calls)


async def test_a_retry_after_a_restart_is_refused_and_moves_nothing(tmp_path: Path) -> None:
    api = await Api(tmp_path).start()
    status, first = await api.command("planner", MOVE)
    assert (status, first["outcome"]) == (200, "executed"), first
    again = await _started_again(api, after_s=60)
    try:
        status, body = await again.command("planner", MOVE)
        assert (status, body["error_code"], body["reason"]) == (
            409, "MESSAGE_ID_CONFLICT", "decided_before_restart"), body
        assert _moves(again) == 0
        entry = again.entry(body["audit_id"])
        assert (entry["principal"], entry["message_id"], entry["outcome"]) == (
            "planner", MOVE["message_id"], "denied"), entry
        # Another principal's id is its own; a new id moves; a stop under the id runs.
        status, body = await again.command("ops", MOVE)
        assert (status, body["outcome"]) == (200, "executed"), body
        stop = {"action": "stop", "message_id": "7d3f5a52-5e0b-4c39-9d61-2f6a4f0f0a11"}
        assert (await again.command("planner", stop))[1]["outcome"] == "executed"
    finally:
        await _closed(again)


async def test_a_retry_after_the_ten_minutes_is_a_new_command(tmp_path: Path) -> None:
    api = await Api(tmp_path).start()
    assert (await api.command("planner", MOVE))[0] == 200
    again = await _started_again(api, after_s=601)
    try:
        status, body = await again.command("planner", MOVE)
        assert (status, body["outcome"]) == (200, "executed"), body
        assert _moves(again) == 1
    finally:
        await _closed(again)
