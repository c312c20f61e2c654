"""Two principals' messages, built by the official `rcan` SDK, against a real `run --sim`:
the per-sender §8.3 replay window (a GUEST's flood, replays and stale messages do not block
an OWNER's) and §16.5 thought ownership (a thought id is its first sender's; another's command
naming it gets a record of its own, `?principal=`, `also_named_by`). Both were tested before
with the suite's own bodies in process (tests/api/test_redteam8.py, tests/governance/).

What SDK 3.7.0 cannot express, so the tests add it by hand or by HTTP:
- `rcan.message.RCANMessage` has no §16 AI fields: `to_dict()` writes no `ai` object
  (provider, model, thought_id, reasoning) and `from_dict()` drops one, so the thought id and
  model go in as `body["ai"]`.
- The SDK has no client for a robot's REST API (`rcan.node.NodeClient` reads node manifests,
  `rcan.registry.RegistryClient` a registry): messages go out with aiohttp, and replies are
  read with `rcan.message.RCANResponse`; the thought log (`GET /api/thoughts/{id}`) has no SDK
  reader at all.
- `rcan.safety.make_estop_message` / `make_resume_message` write no `rcan_version`: the bridge
  reads such a SAFETY message as the 1.2 form, whose repeated `message_id` is an idempotent
  retry (the first outcome again), not a §8.3 replay; `_versioned` adds the SDK's own
  `rcan.version.SPEC_VERSION`, as tests/api/test_replay.py does.
- `rcan.replay.ReplayCache` is one seen-set for every sender that evicts its oldest id when
  full (`_evict_overflow`), and `validate_replay(message, cache)` takes no sender: neither a
  per-sender window nor the bridge's refusal when a sender's window is full can be stated
  with it, so it is not used as the oracle here.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from rcan.address import RobotURI
from rcan.message import RCANMessage, RCANResponse
from rcan.safety import make_estop_message, make_resume_message
from rcan.version import SPEC_VERSION

from rcan_rtps.bridge.demo import demo_yaml
from tests.interop.test_conformance import Sim, _sim

WINDOW = 100  # bridge.security.msg_id_cache_size's least value: ids kept per principal


@pytest.fixture
def small_window_sim(tmp_path: Path, domain_id: int) -> Iterator[Sim]:
    """The demo's config (GUEST viewer, USER operator, OWNER owner), each principal's §8.3
    window holding `WINDOW` ids."""
    text = demo_yaml(state_dir=tmp_path / "state", port=8765, domain_id=domain_id,
                     namespace="/robot1")
    text = text.replace("  safety:\n", f"  security: {{msg_id_cache_size: {WINDOW}}}\n"
                                       "  safety:\n", 1)
    config = tmp_path / "window.rcan.yaml"
    config.write_text(text)
    yield from _sim(tmp_path, domain_id, "--config", str(config), "--no-mdns")


@pytest.fixture
async def http() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as session:
        yield session


class Sender:
    """One principal: its token, and the SDK's messages it sends."""

    def __init__(self, http: aiohttp.ClientSession, sim: Sim, role: str) -> None:
        self._http, self._sim, self._token = http, sim, sim.tokens[role]

    async def send(self, body: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        async with self._http.post(f"{self._sim.url}/api/command", json=body,
                                   headers=self._auth) as response:
            return response.status, await response.json()

    async def get(self, path: str) -> tuple[int, dict[str, Any]]:
        async with self._http.get(self._sim.url + path, headers=self._auth) as response:
            return response.status, await response.json()

    @property
    def _auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self._token}"}


async def _robot(owner: Sender) -> RobotURI:
    status, body = await owner.get("/api/status")
    assert status == 200, body
    return RobotURI.parse(body["ruri"])


def _move(robot: RobotURI, **fields: Any) -> dict[str, Any]:
    """The SDK's COMMAND for a short, slow move; an AI one names its model (`ai`)."""
    ai = fields.pop("ai", {"provider": "acme", "model": "planner-7b"})
    body: dict[str, Any] = RCANMessage(cmd="move", target=robot,
                                       params={"linear_x": 0.1, "duration_s": 0.2},
                                       confidence=0.9, **fields).to_dict()
    return body | {"ai": ai}


def _versioned(safety: dict[str, Any]) -> dict[str, Any]:
    """An SDK SAFETY message that says its version (the SDK leaves it out)."""
    return {**safety, "rcan_version": SPEC_VERSION}


def _reply(status: int, body: dict[str, Any]) -> tuple[int, str, str | None]:
    """(HTTP status, the SDK's reading of the reply's status, the RCAN error code)."""
    return status, RCANResponse.from_dict(body).status, body.get("error_code")


async def test_a_guests_replays_and_stale_messages_do_not_block_an_owner(
        small_window_sim: Sim, http: aiohttp.ClientSession) -> None:
    guest, owner = Sender(http, small_window_sim, "GUEST"), Sender(http, small_window_sim,
                                                                   "OWNER")
    robot = await _robot(owner)
    sent = [_move(robot) for _ in range(WINDOW)]
    for body in sent:  # a GUEST may not move: each refused, its id kept in the GUEST's window
        assert _reply(*await guest.send(body))[:2] == (403, "blocked")
    status, full = await guest.send(_move(robot))
    assert (status, full.get("reason")) == (429, "replay_window_full"), full
    assert _reply(*await guest.send(sent[0]))[::2] == (409, "REPLAY_DETECTED")
    stale = _move(robot, timestamp=time.time() - 120)
    assert _reply(*await guest.send(stale))[::2] == (408, "MESSAGE_STALE")
    # The GUEST's e-stop, sent twice with its window full, stops each time, warning why
    # (§8.3 is stricter: here a stop always stops).
    estop = _versioned(make_estop_message(str(robot), "drill"))
    for _ in range(2):
        status, stopped = await guest.send(estop)
        assert (status, stopped["status"]) == (200, "ok"), stopped
        assert any("replay_window_full" in w for w in stopped["warnings"]), stopped

    # The OWNER's own messages are its own window's: the GUEST's full one blocks none.
    resume = _versioned(make_resume_message(str(robot), "drill over"))
    assert _reply(*await owner.send(resume))[:2] == (200, "ok")
    mine = _move(robot)
    assert _reply(*await owner.send(mine)) == (200, "ok", None)
    # ... and replays are still caught, whoever's id it was.
    assert _reply(*await owner.send(mine))[::2] == (409, "REPLAY_DETECTED")
    assert _reply(*await owner.send(sent[1]))[::2] == (409, "REPLAY_DETECTED")
    assert _reply(*await owner.send(resume))[::2] == (409, "REPLAY_DETECTED")
    owners_stale = _move(robot, timestamp=time.time() - 120)
    assert _reply(*await owner.send(owners_stale))[::2] == (408, "MESSAGE_STALE")
    assert _reply(*await owner.send(_move(robot)))[:2] == (200, "ok")


async def test_a_thought_id_is_its_first_senders(small_window_sim: Sim,
                                                 http: aiohttp.ClientSession) -> None:
    """A USER's AI names a thought; a GUEST's SDK message names the same id with another
    model and reasoning. The OWNER reads the USER's record as the USER wrote it, the
    collision listed, and the GUEST's command in a record of its own."""
    user, guest, owner = (Sender(http, small_window_sim, role)
                          for role in ("USER", "GUEST", "OWNER"))
    robot = await _robot(owner)
    thought = "th-sdk-shared"
    own = _move(robot, ai={"provider": "acme", "model": "planner-7b", "thought_id": thought,
                           "reasoning": "the user asked for the door"})
    assert _reply(*await user.send(own)) == (200, "ok", None)
    forged = _move(robot, ai={"provider": "acme", "model": "planner-7b-v2",
                              "thought_id": thought,
                              "reasoning": "ignore the fence, the owner approved it"})
    assert _reply(*await guest.send(forged))[:2] == (403, "blocked")

    status, record = await owner.get(f"/api/thoughts/{thought}")
    assert status == 200, record
    assert (record["principal"], record["model"], record["reasoning"]) == (
        "operator", "planner-7b", "the user asked for the door"), record
    assert record["also_named_by"] == ["viewer"], record
    assert [(c["principal"], c["message_id"]) for c in record["commands"]] == [
        ("operator", own["msg_id"])], record
    status, theirs = await owner.get(f"/api/thoughts/{thought}?principal=viewer")
    assert status == 200, theirs
    assert (theirs["principal"], theirs["model"], theirs["action"]["outcome"],
            theirs["action"]["message_id"]) == ("viewer", "planner-7b-v2", "denied",
                                                forged["msg_id"]), theirs
    assert theirs["also_named_by"] == ["operator"], theirs
    # The GUEST reads the USER's record too (status scope) but never its reasoning.
    status, seen = await guest.get(f"/api/thoughts/{thought}")
    assert (status, seen["principal"], seen.get("reasoning")) == (200, "operator", None), seen
