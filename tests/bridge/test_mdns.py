"""mDNS: the advert and its TXT as a zeroconf browser sees them, re-announcement, withdrawal,
and `rcan-rtps discover`. Zeroconf is bound to 127.0.0.1 only, and the tests that send packets
run only inside a private network namespace (`scripts/netns`), so nothing leaves the machine."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import socket
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from rcan_rtps.bridge.mdns import (
    SERVICE_TYPE,
    Advert,
    DiscoveredRobot,
    RcanAdvertiser,
    RcanBrowser,
    txt_records,
)
from rcan_rtps.cli.main import main
from rcan_rtps.config import RcanConfig, loads_config

# mDNS is one multicast group for the whole network namespace and these adverts share names
# (so do the demo's): what advertises runs in the serial phase (scripts/pytest_phases.sh).
pytestmark = pytest.mark.serial
LOOPBACK = ["127.0.0.1"]
INSTANCE = "clearpath-husky-a200-0001"
CONFIG = """\
robot: {ruri: "rcan://registry.local/clearpath/husky/a200-0001", name: Husky A200}
bridge:
  ros2: {distro: kilted}
  api: {auth_token_env: T}
  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0}
  %s
"""


def _isolated() -> bool:
    """Only a loopback interface: we are in a private network namespace."""
    return [name for _, name in socket.if_nameindex()] == ["lo"]


needs_netns = pytest.mark.skipif(
    not _isolated(), reason="mDNS tests send multicast: run them under scripts/netns")


def _config(extra: str = "") -> RcanConfig:
    return loads_config(CONFIG % extra, env={"T": "t" * 32})


def test_txt_records_follow_the_profile() -> None:
    txt = txt_records(_config(), api_url="http://10.0.0.5:8765")
    assert txt == {
        "ruri": "rcan://registry.local/clearpath/husky/a200-0001",
        "role": "USER", "version": "1.2", "spec": "1.2", "versions": "1.2,3.2",
        "rcan_version": "3.2", "bridge": "ros2",
        "distro": "kilted", "api": "http://10.0.0.5:8765",
        "status_endpoint": "http://10.0.0.5:8765/api/status", "model": "husky",
        "name": "Husky A200",
        "caps": "move,arm_joint,navigate,dock,stop,estop,clear_estop,lock,unlock",
    }


def test_role_is_the_lowest_that_may_command() -> None:
    raised = _config("rbac: {action_roles: {move: LEASEE, arm_joint: OWNER, navigate: LEASEE,"
                     " dock: LEASEE, stop: LEASEE}}")
    assert txt_records(raised, api_url="http://h:1")["role"] == "LEASEE"


def test_advert_instance_and_port() -> None:
    advert = Advert.from_config(_config(), api_url="https://10.0.0.5:9443/",
                                addresses=["10.0.0.5"])
    assert (advert.instance, advert.port, advert.addresses) == (INSTANCE, 9443, ("10.0.0.5",))
    assert advert.txt["status_endpoint"] == "https://10.0.0.5:9443/api/status"


def test_advert_for_a_server_bound_to_one_address() -> None:
    advert = Advert.for_server(_config(), host="127.0.0.1", port=8765, tls=True)
    assert advert.addresses == ("127.0.0.1",)
    assert advert.txt["api"] == "https://127.0.0.1:8765"


def test_advert_for_a_wildcard_bind_names_the_mdns_host() -> None:
    advert = Advert.for_server(_config(), host="0.0.0.0", port=8765)
    assert advert.txt["api"] == f"http://{INSTANCE}.local:8765"
    assert advert.addresses
    for address in advert.addresses:
        socket.inet_aton(address)
    loopback = [a for a in advert.addresses if a.startswith("127.")]
    assert loopback in ([], ["127.0.0.1"])
    assert not loopback or advert.addresses == ("127.0.0.1",)


def _advert(port: int = 18765, address: str = "127.0.0.1") -> Advert:
    return Advert.from_config(_config(), api_url=f"http://{address}:{port}",
                              addresses=[address])


def _has(instance: str, **txt: str):  # type: ignore[no-untyped-def]
    def check(robots: list[DiscoveredRobot]) -> bool:
        return any(r.instance == instance and all(r.txt.get(k) == v for k, v in txt.items())
                   for r in robots)
    return check


@pytest.fixture
async def browser() -> AsyncIterator[RcanBrowser]:
    async with RcanBrowser(interfaces=LOOPBACK) as found:
        yield found


@needs_netns
async def test_browser_sees_the_txt_records(browser: RcanBrowser) -> None:
    async with RcanAdvertiser(_advert(), interfaces=LOOPBACK):
        robots = await browser.wait_for(_has(INSTANCE), timeout_s=30)
    robot = next(r for r in robots if r.instance == INSTANCE)
    assert robot.txt == _advert().txt
    assert (robot.port, robot.addresses, robot.host) == (18765, ["127.0.0.1"],
                                                         f"{INSTANCE}.local.")


@needs_netns
async def test_reannounced_on_endpoint_and_address_change(browser: RcanBrowser) -> None:
    async with RcanAdvertiser(_advert(), interfaces=LOOPBACK) as advertiser:
        await browser.wait_for(_has(INSTANCE), timeout_s=30)
        assert not await advertiser.update(_advert())  # nothing changed: nothing sent
        assert await advertiser.update(_advert(port=18766))
        robots = await browser.wait_for(
            _has(INSTANCE, status_endpoint="http://127.0.0.1:18766/api/status"), timeout_s=30)
        assert next(r for r in robots if r.instance == INSTANCE).port == 18766
        assert await advertiser.update(_advert(port=18766, address="127.0.0.2"))

        def moved(robots: list[DiscoveredRobot]) -> bool:
            return any(r.instance == INSTANCE and r.addresses == ["127.0.0.2"] for r in robots)

        await browser.wait_for(moved, timeout_s=30)


@needs_netns
async def test_follow_reannounces_what_the_provider_says(browser: RcanBrowser) -> None:
    current = [_advert()]
    async with RcanAdvertiser(current[0], interfaces=LOOPBACK) as advertiser:
        advertiser.follow(lambda: current[0], interval_s=0.05)
        await browser.wait_for(_has(INSTANCE), timeout_s=30)
        current[0] = _advert(port=18799)
        await browser.wait_for(_has(INSTANCE, api="http://127.0.0.1:18799"), timeout_s=30)


@needs_netns
async def test_withdrawn_on_shutdown(browser: RcanBrowser) -> None:
    async with RcanAdvertiser(_advert(), interfaces=LOOPBACK):
        await browser.wait_for(_has(INSTANCE), timeout_s=30)
    await browser.wait_for(lambda robots: not _has(INSTANCE)(robots), timeout_s=30)


@needs_netns
async def test_discover_command_lists_robots_with_their_txt(tmp_path: Path) -> None:
    async with RcanAdvertiser(_advert(), interfaces=LOOPBACK):
        async with RcanBrowser(interfaces=LOOPBACK) as browser:  # advertised by now
            await browser.wait_for(_has(INSTANCE), timeout_s=30)
        out = io.StringIO()

        def run() -> int:
            with contextlib.redirect_stdout(out):
                # The window counts from the command's start (zeroconf's threads, its first
                # query 20-120 ms in): 1.5 s missed the advert once on a busy machine (CI).
                return main(["discover", "--timeout", "5", "--json",
                             "--interface", "127.0.0.1"])

        assert await asyncio.to_thread(run) == 0
    found = [json.loads(line) for line in out.getvalue().splitlines()]
    robot = next(r for r in found if r["instance"] == INSTANCE)
    assert robot["txt"]["ruri"] == "rcan://registry.local/clearpath/husky/a200-0001"
    assert robot["txt"]["spec"] == "1.2"
    assert robot["addresses"] == ["127.0.0.1"]


def test_discover_rejects_a_bad_timeout(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["discover", "--timeout", "-1"]) == 1
    assert "--timeout" in capsys.readouterr().err


def test_service_type() -> None:
    assert SERVICE_TYPE == "_rcan._tcp.local."


# What a peer says is shown, never obeyed: terminal escape sequences (ESC, the 8-bit CSI
# \x9b, BEL, a carriage return, a bidi override) in an advert's name or TXT.
HOSTILE = "evil\x1b]0;owned\x07\x1b[2J\r\x9b31m\u202e"
HOSTILE_NAME = "evil\x9b2J\u202e"  # zeroconf sends no ASCII control character in a name


@needs_netns
async def test_discover_shows_a_hostile_adverts_control_characters_escaped() -> None:
    """Red team 19: `rcan-rtps discover` printed an advert's instance name and TXT values to
    the terminal as they came, so any peer on the network could send the operator's
    terminal escape sequences (clear the screen, retitle the window, rewrite or hide the
    robots listed above it, and on some terminals write the clipboard). They are now shown
    escaped (`\\x1b`); printable text, non-ASCII letters included, is shown as it is."""
    from zeroconf.asyncio import AsyncServiceInfo, AsyncZeroconf

    hostile = AsyncServiceInfo(
        SERVICE_TYPE, f"rover-{HOSTILE_NAME}.{SERVICE_TYPE}", port=18765,
        properties={"ruri": f"rcan://x/{HOSTILE}", f"k{HOSTILE}": HOSTILE, "name": "Rövar"},
        server="hostile.local.", addresses=[socket.inet_aton("127.0.0.1")])
    peer = AsyncZeroconf(interfaces=LOOPBACK)
    try:
        await (await peer.async_register_service(hostile))
        async with RcanBrowser(interfaces=LOOPBACK) as browser:
            await browser.wait_for(lambda robots: any(r.instance.startswith("rover-")
                                                      for r in robots), timeout_s=30)
        out = io.StringIO()

        def run() -> int:
            with contextlib.redirect_stdout(out):
                return main(["discover", "--timeout", "5", "--interface", "127.0.0.1"])

        assert await asyncio.to_thread(run) == 0
    finally:
        await peer.async_close()
    shown = out.getvalue()
    assert "rover-evil" in shown and "Rövar" in shown
    assert not [c for c in shown if not c.isprintable() and c != "\n"], repr(shown)
    assert "\\x1b]0;owned\\x07" in shown
