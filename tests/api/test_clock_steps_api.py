"""Red team 21 through the app: the wall clock stepped while the bridge runs, or between two
runs. A step may refuse or expire; it never runs a command twice nor takes a replay.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import aiohttp
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from jwthelpers import sign_jwt, write_jwks

from tests.api.apihelpers import Api
from tests.api.test_rcan3_messages import sdk_command
from tests.api.test_retry_after_restart import _closed, _moves

HOUR = 3600.0
MOVE = {"action": "move", "message_id": "0b4e7a44-3f0e-4a86-9c55-5d3a3b7f2c10",
        "params": {"linear_x": 0.2, "duration_s": 1.0}}


async def _restarted_behind(api: Api, behind_s: float) -> Api:
    """The bridge stopped and started again on the same audit log at once, its wall clock
    `behind_s` behind the time the log's last entry was written (stepped back, or a start
    before NTP set it); its e-stop, latched by the motion the first run left, cleared."""
    then = api.clock.time()
    await api.close()
    again = Api(api.tmp)
    again.clock.step(then - behind_s - again.clock.time())  # the wall clock alone
    await again.start()
    await again.gov.start()
    status, _ = await again.command("ops", {"action": "clear_estop"})
    assert status == 200
    return again


async def test_a_retry_after_a_restart_behind_the_log_is_refused(tmp_path: Path) -> None:
    """The log's entries seem to come from the future: the move the first run decided is
    still a decided one (its retry within the ttl refused), not a new first time."""
    api = await Api(tmp_path).start()
    status, first = await api.command("planner", MOVE)
    assert (status, first["outcome"]) == (200, "executed"), first
    again = await _restarted_behind(api, HOUR)
    try:
        status, body = await again.command("planner", MOVE)
        assert (status, body["reason"]) == (409, "decided_before_restart"), body
        assert _moves(again) == 0
    finally:
        await _closed(again)


async def test_a_replay_after_a_restart_behind_the_log_and_ntp_is_refused(
        tmp_path: Path) -> None:
    """The first run took a command; the bridge starts again an hour behind; NTP steps the
    clock forward: the command, sent again within its window, is a replay."""
    api = await Api(tmp_path).start()
    msg = sdk_command(api, "move", {"linear_x": 0.3, "duration_s": 1.0})
    assert (await api.command("planner", msg))[0] == 200
    again = await _restarted_behind(api, HOUR)
    try:
        again.clock.step(HOUR + 3)
        status, body = await again.command("planner", msg)
        assert (status, body["error_code"]) == (409, "REPLAY_DETECTED"), body
        assert _moves(again) == 0
    finally:
        await _closed(again)


async def test_a_replay_after_a_step_back_under_a_running_bridge_is_refused(
        api: Api) -> None:
    """NTP steps back 5 s just after the window forgot a command's id: the command, fresh
    again by the clock now, is refused as stale, and nothing moves."""
    msg = sdk_command(api, "move", {"linear_x": 0.3, "duration_s": 1.0})
    assert (await api.command("planner", msg))[0] == 200
    api.clock.advance(32)
    assert (await api.command("planner", sdk_command(api, "stop")))[0] == 200  # forgets it
    api.clock.step(-5)
    status, body = await api.command("planner", msg)
    assert (status, body["error_code"]) == (408, "MESSAGE_STALE"), body
    assert _moves(api) == 1


async def test_a_jwt_expired_before_a_step_back_stays_expired(tmp_path: Path) -> None:
    """A token used, then expired (exp + the 30 s leeway) while the bridge checked another;
    the clock steps back an hour: the token, unexpired by the clock now, is still refused."""
    key = Ed25519PrivateKey.generate()
    jwks = write_jwks(tmp_path / "jwks.json", {"idp": key})
    api = await Api(tmp_path, api_extra=f"jwt: {{jwks: '{jwks}', audience: rcan-bridge}}"
                    ).start()

    def token(exp_in_s: float) -> str:
        body = {"sub": "agent", "role": "USER", "aud": "rcan-bridge",
                "exp": api.clock.time() + exp_in_s}
        return sign_jwt(key, body, {"alg": "EdDSA", "kid": "idp"})

    async def status(bearer: str) -> tuple[int, Any]:
        async with api.http.get("/api/status",
                                headers={"Authorization": f"Bearer {bearer}"}) as resp:
            return resp.status, await resp.json()

    try:
        short = token(60)
        assert (await status(short))[0] == 200
        api.clock.advance(120)
        assert (await status(token(60)))[0] == 200  # the bridge reads the time
        api.clock.step(-HOUR)
        code, reply = await status(short)
        assert (code, reply.get("reason")) == (401, "jwt_expired"), reply
    finally:
        await api.close()


async def test_after_a_step_back_of_an_hour_stops_still_stop(api: Api) -> None:
    """An hour back (the clock had been set ahead, NTP sets it right): a new move is refused
    as stale until the clock passes the time it was stepped back from; a stop and an e-stop,
    stamped by the clock now, still stop."""
    assert (await api.command("planner", sdk_command(api, "move", {"linear_x": 0.3})))[0] \
        == 200
    api.clock.step(-HOUR)
    status, body = await api.command("planner", sdk_command(api, "move", {"linear_x": 0.3}))
    assert (status, body["reason"]) == (
        408, "older_than_30_s_before_the_clock_went_back"), body
    entry = api.entry(body["audit_id"])  # refused on the record, saying why
    assert (entry["outcome"], entry["deny_reason"]) == (
        "denied", "MESSAGE_STALE:older_than_30_s_before_the_clock_went_back"), entry
    status, body = await api.command("planner", sdk_command(api, "stop"))
    assert (status, body["outcome"]) == (200, "executed"), body
    status, body = await api.command("viewer", sdk_command(api, "estop"))
    assert (status, body["outcome"]) == (200, "executed"), body
    assert [a for a, _ in api.dispatcher.calls] == ["move", "stop", "estop"]


async def test_a_restart_ends_the_refusals_of_a_step_back(tmp_path: Path) -> None:
    """After an hour back, a new run (which has read no later time) takes new messages."""
    api = await Api(tmp_path).start()
    assert (await api.command("planner", sdk_command(api, "move", {"linear_x": 0.3})))[0] \
        == 200
    again = await _restarted_behind(api, HOUR)
    try:
        status, body = await again.command("planner",
                                           sdk_command(again, "move", {"linear_x": 0.3}))
        assert (status, body["outcome"]) == (200, "executed"), body
    finally:
        await _closed(again)


async def test_a_jwt_that_expired_while_no_token_was_checked_stays_expired(
        tmp_path: Path) -> None:
    """No token is checked between a token's expiry and the step back; the governor's sweep
    read the time meanwhile (every 50 ms as it runs): the token is still refused."""
    key = Ed25519PrivateKey.generate()
    jwks = write_jwks(tmp_path / "jwks.json", {"idp": key})
    api = await Api(tmp_path, api_extra=f"jwt: {{jwks: '{jwks}', audience: rcan-bridge}}"
                    ).start()
    body = {"sub": "agent", "role": "USER", "aud": "rcan-bridge", "exp": api.clock.time() + 60}
    short = sign_jwt(key, body, {"alg": "EdDSA", "kid": "idp"})
    try:
        async with api.http.get("/api/status",
                                headers={"Authorization": f"Bearer {short}"}) as resp:
            assert resp.status == 200
        api.clock.advance(120)
        await api.gov.sweep()
        api.clock.step(-HOUR)
        async with api.http.get("/api/status",
                                headers={"Authorization": f"Bearer {short}"}) as resp:
            assert (resp.status, (await resp.json()).get("reason")) == (401, "jwt_expired")
    finally:
        await api.close()


async def test_a_step_back_keeps_no_websocket_ticket_past_its_30_s(api: Api) -> None:
    """A ticket lives 30 s of monotonic time: an hour back, it has expired all the same."""
    status, body = await api.call("POST", "/api/ws-ticket", "ops")
    assert status == 200, body
    api.clock.step(-HOUR)
    api.clock.advance(31)
    with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
        async with api.http.ws_connect(f"/api/ws?ticket={body['ticket']}"):
            pass
    assert refused.value.status == 401
