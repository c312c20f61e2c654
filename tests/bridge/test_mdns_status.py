"""STATUS in the mDNS advert (bridge spec §3.1 flow 2 steps 3–4, §5.1; spec audit G10).

Before, the advert carried where STATUS is (`status_endpoint`) but nothing of it: a registry
collecting STATUS "from each bridge's mDNS advertisement" learnt nothing of an e-stopped or
silent robot. Now a running bridge announces STATUS's `state` and its newest telemetry's time
(to the minute), re-announced when they change.
"""

from __future__ import annotations

import time
from pathlib import Path

import aiohttp
import pytest
from interop.bridge_rig import bridge_config
from test_expected_stillness import ODOM, telemetry_of

from rcan_rtps.bridge.mdns import RcanBrowser, live_records
from rcan_rtps.bridge.runtime import Bridge, BridgeOptions
from tests.bridge.test_mdns import LOOPBACK, needs_netns

TOKEN = "t" * 32
INSTANCE = "acme-rover-unit-0001"  # bridge_rig's robot


async def test_state_and_the_newest_telemetrys_minute_from_a_status(tmp_path: Path,
                                                                   domain_id: int) -> None:
    config = bridge_config(tmp_path, domain_id)
    with telemetry_of("advert", config, latched=False) as (node, telemetry):
        assert live_records(telemetry.status(pending_auth=0, counted=False)) == {
            "state": "offline"}  # no telemetry yet: no time either
        before = telemetry.status(pending_auth=0).seq
        telemetry._on_odom(node.values.build(ODOM, {}))  # at rest
        heard = time.time()
        records = live_records(telemetry.status(pending_auth=0, counted=False))
        assert telemetry.status(pending_auth=0).seq == before + 1  # the advert's look took none
    assert records["state"] == "idle", records
    assert int(records["telemetry_ts"]) % 60 == 0
    assert heard - 60 - 1 <= int(records["telemetry_ts"]) <= heard, (records, heard)


async def _estop(url: str) -> None:
    async with aiohttp.ClientSession() as http, http.post(
            f"{url}/api/command", json={"action": "estop"},
            headers={"Authorization": f"Bearer {TOKEN}"}) as answer:
        assert (await answer.json())["outcome"] in ("executed", "failed"), await answer.text()


@pytest.mark.serial  # one multicast group for the whole namespace (as tests/bridge/test_mdns)
@needs_netns
async def test_a_running_bridge_announces_its_state_as_it_changes(tmp_path: Path,
                                                                   domain_id: int) -> None:
    bridge = Bridge(bridge_config(tmp_path, domain_id), BridgeOptions(
        port=0, host="127.0.0.1", mdns=True, mdns_interfaces=LOOPBACK,
        env={"RCAN_BRIDGE_TOKEN": TOKEN}))
    await bridge.start()
    try:
        async with RcanBrowser(interfaces=LOOPBACK) as browser:
            def state(robots: list, want: str) -> bool:  # type: ignore[type-arg]
                return any(r.instance == INSTANCE and r.txt.get("state") == want
                           for r in robots)

            robots = await browser.wait_for(lambda found: state(found, "offline"),
                                            timeout_s=30)
            seen = next(r for r in robots if r.instance == INSTANCE)
            assert "telemetry_ts" not in seen.txt, seen.txt  # no telemetry: no time
            assert bridge.url is not None
            await _estop(bridge.url)  # latched (its Bool has no subscriber here)
            await browser.wait_for(lambda found: state(found, "estop"), timeout_s=30)
    finally:
        await bridge.stop()
