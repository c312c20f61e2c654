"""The conformance runner's INVOKE probes (§19) against the API over the in-memory robot (the
run against a real `run --sim` is tests/interop/test_conformance.py), and how the runner picks
the skill it invokes: one the bridge lists that moves nothing, or the one it is told."""

from __future__ import annotations

from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from rcan_rtps.bridge.demo import demo_config
from rcan_rtps.conformance import load_suite
from rcan_rtps.conformance.bridge import BridgeUnderTest, ProbeError, Skill, still_skill
from rcan_rtps.conformance.probes import PROBES
from tests.api.apihelpers import TOKENS, Api

SKILLS = ("skills: {nudge: {action: move, params: {linear_x: 0.3}, allow: [duration_s]}, "
          "hold_still: {action: move, params: {linear_x: 0, duration_s: 0.5}}}")
ROLE_TOKENS = {"OWNER": TOKENS["ops"], "USER": TOKENS["planner"], "GUEST": TOKENS["viewer"]}
INVOKE_CASES = ["L1-INVOKE-001", "L1-INVOKE-002", "L1-INVOKE-003", "L2-INVOKE-001",
                "L3-INVOKE-001"]


def skill(name: str, *, action: str = "move", params: dict[str, Any] | None = None,
          allow: list[str] | None = None) -> Skill:
    return Skill(name=name, action=action, role="USER", params=params or {}, allow=allow or [])


def test_the_demos_still_skill_is_hold_still(tmp_path: Path) -> None:
    config = demo_config(state_dir=tmp_path, port=8765, domain_id=0, namespace="/robot1",
                         env={})
    skills = {n: skill(n, action=s.action, params=dict(s.params), allow=list(s.allow))
              for n, s in config.bridge.skills.items()}
    found = still_skill(skills)
    assert found is not None and found.name == "hold_still"


@pytest.mark.parametrize("declared", [
    skill("a", params={"linear_x": 0.3, "duration_s": 1}),  # it moves
    skill("a", params={"linear_x": 0}),  # held until stopped: outlives the case
    skill("a", params={"duration_s": 1}, allow=["linear_x"]),  # the invoker sets it
    skill("a", action="navigate", params={"x": 0, "y": 0, "yaw": 0}),  # a goal: it may move
    skill("a", params={"angular_z": 0.1, "duration_s": 1}),
])
def test_a_skill_that_may_move_is_never_picked(declared: Skill) -> None:
    assert still_skill({"a": declared}) is None


def test_the_still_skill_is_the_first_by_name() -> None:
    still = {"duration_s": 0.2, "linear_x": 0.0, "linear_y": 0, "angular_z": 0}
    assert still_skill({"b": skill("b", params=still), "a": skill("a", params=still)}) == skill(
        "a", params=still)


@pytest.fixture
async def api(tmp_path: Path) -> AsyncIterator[Api]:
    harness = await Api(tmp_path, bridge_extra=SKILLS).start()
    yield harness
    await harness.close()


@pytest.fixture
async def session() -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession() as client:
        yield client


def bridge(api: Api, session: aiohttp.ClientSession, skill: str | None = None
           ) -> BridgeUnderTest:
    return BridgeUnderTest(session, str(api.http.make_url("")), ROLE_TOKENS, skill=skill)


@pytest.mark.parametrize("case_id", INVOKE_CASES)
async def test_each_invoke_probe_passes_and_moves_nothing(api: Api,
                                                          session: aiohttp.ClientSession,
                                                          case_id: str) -> None:
    [case] = [c for c in load_suite().cases if c.id == case_id]
    verdict = await PROBES[case_id](bridge(api, session), case)
    assert verdict.outcome == "pass", verdict.detail
    moves = [p for a, p in api.dispatcher.calls if a == "move"]
    assert all(p["linear_x"] == p["linear_y"] == p["angular_z"] == 0 for p in moves), moves
    assert all(a in ("move", "estop", "clear_estop") for a, _ in api.dispatcher.calls)


async def test_the_skill_named_is_the_one_invoked(api: Api,
                                                  session: aiohttp.ClientSession) -> None:
    assert (await bridge(api, session).skill()).name == "hold_still"
    assert (await bridge(api, session, "nudge").skill()).name == "nudge"
    with pytest.raises(ProbeError, match=r"--skill fly: not listed.*hold_still, nudge"):
        await bridge(api, session, "fly").skill()


async def test_without_a_still_skill_the_runner_asks_for_one(
        tmp_path: Path, session: aiohttp.ClientSession) -> None:
    harness = await Api(tmp_path, bridge_extra="skills: {nudge: {action: move, params: "
                        "{linear_x: 0.3}, allow: [duration_s]}}").start()
    try:
        with pytest.raises(ProbeError, match="name a harmless one with --skill"):
            await bridge(harness, session).skill()
    finally:
        await harness.close()
    assert harness.dispatcher.calls == []
