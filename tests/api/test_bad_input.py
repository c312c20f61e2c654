"""Bad input at the HTTP edge: each gets the profile's code, is audited where the profile says
(authenticated pre-command refusals: yes; unauthenticated: no), and nothing answers 5xx."""

from __future__ import annotations

import asyncio
import http.client
import json
import threading
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.api.apihelpers import TOKENS, Api, auth

MB = 1024 * 1024


async def _schema_refusal(api: Api, raw: bytes, path: str) -> dict[str, Any]:
    before = len(api.entries)
    status, body = await api.command("planner", raw=raw)
    assert status == 400, body
    assert (body["outcome"], body["error_code"], body["path"]) == (
        "denied", "SCHEMA_VALIDATION_FAILED", path)
    entry = api.entry(body["audit_id"])
    assert len(api.entries) == before + 1
    assert (entry["event"], entry["principal"], entry["outcome"]) == (
        "COMMAND_REJECTED", "planner", "denied")
    assert entry["deny_reason"] == f"SCHEMA_VALIDATION_FAILED:{path}"
    assert api.dispatcher.calls == []
    return body


@pytest.mark.parametrize("raw", [
    b'{"action": "move",', b"", b"{}}", b"\xff\xfe{}", b"not json", b'{"action": "move"} x',
    b"[" * 60000, b'{"action":"\xff"}', b'{"action": "move", "params": {"\xc3": 1}}',
], ids=["truncated", "empty", "trailing-brace", "not-utf8", "words", "trailing-junk", "deep",
        "not-utf8-in-string", "not-utf8-in-key"])
async def test_malformed_json(api: Api, raw: bytes) -> None:
    await _schema_refusal(api, raw, "$")


@pytest.mark.parametrize("raw", [b"[]", b'"move"', b"null", b"42"])
async def test_not_an_object(api: Api, raw: bytes) -> None:
    await _schema_refusal(api, raw, "$")


@pytest.mark.parametrize(("body", "path"), [
    ({"action": "move", "params": {"linear_x": "fast"}}, "$.params.linear_x"),
    ({"action": "move", "params": {"linear_x": True}}, "$.params.linear_x"),
    ({"action": "move", "params": {"linear_x": None}}, "$.params.linear_x"),
    ({"action": "move", "params": [0.5]}, "$.params"),
    ({"action": 5}, "$.action"),
    ({"action": "move", "confidence": "high"}, "$.confidence"),
    ({"action": "move", "message_id": "not-a-uuid"}, "$.message_id"),
    ({"action": "arm_joint", "params": {"joints": ["a"], "positions": ["x"],
                                        "duration_s": 1}}, "$.params.positions[0]"),
    ({"action": "navigate", "params": {"x": 1, "y": 2}}, "$.params"),
    ({"message_type": 1, "ruri": 7, "action": "move"}, "$.ruri"),
    ({"action": "move", "bogus": 1}, "$"),
    ({"action": "move", "params": {"linear_z": 1}}, "$.params"),
    # A name with a trailing newline: Python's `$` matched before it (to the robot on 9523eb7).
    ({"action": "arm_joint", "params": {"joints": ["elbow\n"], "positions": [0.5],
                                        "duration_s": 1}}, "$.params.joints[0]"),
    ({"action": "arm_joint", "params": {"joints": ["elbow"], "positions": [0.5],
                                        "duration_s": 1, "group": "arm\n"}}, "$.params.group"),
    ({"action": "lock", "params": {"name": "door\n"}}, "$.params.name"),
    ({"rcan": "3.2", "cmd": "move", "msg_id": "m-1\n", "params": {}}, "$.msg_id"),
    # docs/rcan-profile.md: a msg_id is 1-64 characters of [A-Za-z0-9._:-]
    ({"rcan": "3.2", "cmd": "move", "msg_id": "m" * 65, "params": {}}, "$.msg_id"),
    ({"rcan": "3.2", "cmd": "move", "msg_id": "m 1", "params": {}}, "$.msg_id"),
], ids=lambda v: v if isinstance(v, str) else None)
async def test_wrong_types(api: Api, body: dict[str, Any], path: str) -> None:
    await _schema_refusal(api, json.dumps(body).encode(), path)


@pytest.mark.parametrize("token", [b"NaN", b"Infinity", b"-Infinity", b"nan", b"inf"])
async def test_non_finite_json_tokens(api: Api, token: bytes) -> None:
    raw = b'{"action": "move", "params": {"linear_x": ' + token + b"}}"
    await _schema_refusal(api, raw, "$")


@pytest.mark.parametrize("number", [b"1e400", b"-1e400", b"1e308", b"1" + b"0" * 400,
                                    b"1e10", b"123456789012345678901234567890"])
async def test_huge_numbers(api: Api, number: bytes) -> None:
    raw = b'{"action": "move", "params": {"linear_x": ' + number + b"}}"
    await _schema_refusal(api, raw, "$.params.linear_x")


@pytest.mark.parametrize("action", ["fly", "MOVE", "", "move ", "self_destruct"])
async def test_unknown_actions(api: Api, action: str) -> None:
    await _schema_refusal(api, json.dumps({"action": action}).encode(), "$.action")


async def test_huge_confidence_and_ai_fields(api: Api) -> None:
    await _schema_refusal(api, b'{"action": "move", "confidence": 1e400}', "$.confidence")
    await _schema_refusal(api, json.dumps({"action": "move", "ai_model": "m" * 300}).encode(),
                          "$.ai_model")


@pytest.mark.parametrize("path", ["/api/command", "/api/hitl/authorize", "/api/hitl/deny"])
async def test_one_megabyte_body_is_413_and_audited(api: Api, path: str) -> None:
    raw = b'{"action": "move", "pad": "' + b"x" * MB + b'"}'
    status, body = await api.call("POST", path, "planner", raw=raw)
    assert (status, body["outcome"], body["error_code"]) == (413, "denied", "PAYLOAD_TOO_LARGE")
    entry = api.entry(body["audit_id"])
    assert (entry["principal"], entry["deny_reason"]) == ("planner", "PAYLOAD_TOO_LARGE")
    assert api.dispatcher.calls == []
    # The connection pool stays usable afterwards.
    assert (await api.call("GET", "/api/status", "viewer"))[0] == 200


async def test_one_megabyte_chunked_body_is_413(api: Api) -> None:
    async def chunks() -> AsyncIterator[bytes]:
        yield b'{"action": "move", "pad": "'
        for _ in range(16):
            yield b"x" * (64 * 1024)
        yield b'"}'

    async with api.http.post("/api/command", data=chunks(), headers=auth("planner")) as resp:
        assert resp.status == 413
        assert (await resp.json())["error_code"] == "PAYLOAD_TOO_LARGE"


async def test_one_megabyte_body_without_credentials_is_401_unaudited(api: Api) -> None:
    before = len(api.entries)
    status, body = await api.call("POST", "/api/command", raw=b"x" * MB)
    assert (status, body["error_code"]) == (401, "UNAUTHENTICATED")
    assert len(api.entries) == before


async def test_body_just_under_the_limit_is_read(tmp_path: Path) -> None:
    api = await Api(tmp_path, max_body=1024).start()
    try:
        raw = b'{"action": "move"}'
        raw += b" " * (1024 - len(raw))  # whitespace is JSON too: exactly the limit
        assert (await api.command("planner", raw=raw))[0] == 200
        assert (await api.command("planner", raw=raw + b" "))[0] == 413
    finally:
        await api.close()


async def test_hitl_bodies_are_validated_and_audited(api: Api) -> None:
    status, body = await api.call("POST", "/api/hitl/authorize", "ops", raw=b'{"pending_id": 1}')
    assert (status, body["error_code"], body["path"]) == (400, "SCHEMA_VALIDATION_FAILED",
                                                          "$.pending_id")
    assert api.entry(body["audit_id"])["principal"] == "ops"
    status, body = await api.call("POST", "/api/hitl/deny", "ops", raw=b"{")
    assert (status, body["path"]) == (400, "$")
    status, body = await api.call("POST", "/api/hitl/deny", "ops", raw=b'{"pending_id":"\xff"}')
    assert (status, body["path"]) == (400, "$")
    assert api.entry(body["audit_id"])["deny_reason"] == "SCHEMA_VALIDATION_FAILED:$"
    status, body = await api.call("POST", "/api/hitl/authorize", "ops",
                                  body={"pending_id": "nope"})
    assert (status, body["reason"]) == (404, "pending_not_found")


@pytest.mark.parametrize("query", ["since=-1", "since=abc", "since=1e3", "since=" + "9" * 40,
                                   "limit=0", "limit=100000", "since=%00", "since=١"])
async def test_bad_audit_queries(api: Api, query: str) -> None:
    status, body = await api.call("GET", f"/api/audit?{query}", "lessee")
    assert (status, body["error_code"]) == (400, "SCHEMA_VALIDATION_FAILED")
    assert body["path"].startswith("$.query.")


# -- property: whatever arrives, the answer is JSON and never 5xx --------------------------


class _ServerThread:
    """The app with its governor on an event loop in a thread, for synchronous hypothesis
    tests that talk to it over http.client on 127.0.0.1."""

    def __init__(self, tmp: Path) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.api = self._run(Api(tmp).start())
        url = self.api.http.make_url("/")
        self.host, self.port = url.host or "127.0.0.1", url.port or 0

    def _run(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout=60)

    def request(self, method: str, path: str, body: bytes | None,
                headers: dict[str, str]) -> tuple[int, dict[str, Any]]:
        conn = http.client.HTTPConnection(self.host, self.port, timeout=30)
        try:
            conn.request(method, path, body=body, headers=headers)
            resp = conn.getresponse()
            data = resp.read()
            assert resp.getheader("Content-Type", "").startswith("application/json"), data
            return resp.status, json.loads(data)
        finally:
            conn.close()

    def close(self) -> None:
        self._run(self.api.close())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=10)
        self.loop.close()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[_ServerThread]:
    thread = _ServerThread(tmp_path_factory.mktemp("fuzz"))
    yield thread
    thread.close()


_json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=10), inner,
                                                                max_size=4),
    max_leaves=20,
)
_command_like = st.fixed_dictionaries(
    {"action": st.sampled_from(["move", "arm_joint", "navigate", "stop", "clear_estop", "x"])},
    optional={"params": st.dictionaries(
        st.sampled_from(["linear_x", "linear_y", "angular_z", "x", "y", "yaw", "joints",
                         "positions", "duration_s", "frame_id", "z"]), _json_values,
        max_size=4),
        "confidence": _json_values, "role": _json_values, "message_id": _json_values,
        "ai_model": _json_values, "message_type": _json_values, "ruri": _json_values},
)
_bodies = st.one_of(
    st.binary(max_size=200),
    _json_values.map(lambda v: json.dumps(v).encode()),
    _command_like.map(lambda v: json.dumps(v).encode()),
    _json_values.map(lambda v: json.dumps({"pending_id": v}).encode()),
)
_POSTS = ["/api/command", "/api/hitl/authorize", "/api/hitl/deny", "/api/heartbeat"]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(path=st.sampled_from(_POSTS), body=_bodies,
       who=st.sampled_from(["viewer", "planner", "ops", None]))
def test_no_post_body_makes_a_5xx(server: _ServerThread, path: str, body: bytes,
                                  who: str | None) -> None:
    headers = {"Content-Type": "application/json"}
    if who is not None:
        headers["Authorization"] = f"Bearer {TOKENS[who]}"
    status, answer = server.request("POST", path, body, headers)
    assert status < 500, answer
    assert answer.get("outcome") in (None, "executed", "pending_auth", "denied",
                                     "safety_violation") or answer.get("ok") is True


_query_text = st.text(alphabet=st.characters(codec="utf-8", exclude_characters="\x00"),
                      max_size=30)


@settings(max_examples=100, deadline=None)
@given(path=st.sampled_from(["/api/audit", "/api/audit/verify", "/api/goals/",
                             "/api/status", "/api/hitl/pending", "/api/openapi.json"]),
       value=_query_text)
def test_no_get_makes_a_5xx(server: _ServerThread, path: str, value: str) -> None:
    from urllib.parse import quote

    if path.endswith("/"):
        target = path + (quote(value, safe="") or "x")
    else:
        target = f"{path}?since={quote(value, safe='')}&limit={quote(value, safe='')}"
    status, answer = server.request("GET", target, None, auth("root"))
    assert status < 500, answer


def test_fuzz_decisions_are_all_in_a_valid_chain(server: _ServerThread) -> None:
    status, report = server.request("GET", "/api/audit/verify", None, auth("lessee"))
    assert (status, report["ok"]) == (200, True)
