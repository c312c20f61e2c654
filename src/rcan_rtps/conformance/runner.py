"""Run the suite's cases up to a level against a bridge, one line per case.

Cases run one at a time, in the suite's order (some raise and clear an e-stop, one needs
silence from its principal): a case's probe gets `CASE_TIMEOUT_S` and fails when it overruns.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping

import aiohttp
import msgspec

from .bridge import BridgeUnderTest, MissingToken, ProbeError
from .probes import PROBES, SESSION_WAIT_S, Verdict, failed
from .suite import Case, Level, Suite

CASE_TIMEOUT_S = SESSION_WAIT_S + 15.0


class Result(msgspec.Struct, frozen=True):
    case: Case
    outcome: str  # pass, fail, n/a, out of scope
    detail: str = ""

    def line(self) -> str:
        label = {"pass": "PASS", "fail": "FAIL", "n/a": "N/A ", "out of scope": "OUT "}
        text = f"{label[self.outcome]} {self.case.id:<16} {self.case.name}"
        return f"{text} — {self.detail}" if self.detail else text


async def run_suite(suite: Suite, level: Level, url: str, tokens: Mapping[str, str], *,
                    report: Callable[[Result], None] = lambda r: None,
                    timeout: aiohttp.ClientTimeout | None = None,
                    skill: str | None = None) -> list[Result]:
    """`skill`: the one the INVOKE cases invoke (else one the bridge lists that moves
    nothing; see `BridgeUnderTest`)."""
    results = []
    async with aiohttp.ClientSession(timeout=timeout or aiohttp.ClientTimeout(total=20)) as s:
        bridge = BridgeUnderTest(s, url, tokens, skill=skill)
        for case in suite.upto(level):
            result = await _run_case(bridge, case)
            report(result)
            results.append(result)
    return results


async def unusable(url: str, tokens: Mapping[str, str],
                   timeout: aiohttp.ClientTimeout | None = None) -> str | None:
    """Why no case could run (the bridge does not answer, or refuses a token given: a wrong
    --url or token), or None. Each case would otherwise fail alike, saying so again."""
    async with aiohttp.ClientSession(timeout=timeout or aiohttp.ClientTimeout(total=20)) as s:
        bridge = BridgeUnderTest(s, url, tokens)
        for role in tokens:
            try:
                reply = await bridge.call(role, "GET", "/api/status")
            except (aiohttp.ClientError, asyncio.TimeoutError) as exc:
                return f"cannot reach the bridge at {url} ({exc or type(exc).__name__}): " \
                       "is it running there? (--url)"
            if reply.status == 401:
                return f"the bridge at {url} refused the {role}'s token (401 UNAUTHENTICATED)"
    return None


async def _run_case(bridge: BridgeUnderTest, case: Case) -> Result:
    if case.out_of_scope is not None:
        return Result(case, "out of scope", case.out_of_scope)
    probe = PROBES.get(case.id)
    if probe is None:
        return Result(case, "fail", "no probe for this case in this version of rcan-rtps")
    try:
        verdict = await asyncio.wait_for(probe(bridge, case), CASE_TIMEOUT_S)
    except (MissingToken, ProbeError) as exc:
        verdict = failed(str(exc))
    except asyncio.TimeoutError:
        verdict = failed(f"no verdict within {CASE_TIMEOUT_S:g} s")
    except aiohttp.ClientError as exc:
        verdict = failed(f"the bridge could not be reached: {exc}")
    return _result(case, verdict)


def _result(case: Case, verdict: Verdict) -> Result:
    detail = verdict.detail
    if case.adapted and verdict.outcome != "n/a":
        detail = f"{detail} [adapted: {case.adapted}]" if detail else f"[adapted: {case.adapted}]"
    return Result(case, verdict.outcome, detail)
