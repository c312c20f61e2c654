"""mDNS (zeroconf, async): advertise the robot as `_rcan._tcp.local.` and find RCAN robots.

    Advert.from_config(config, api_url=, addresses=) -> Advert     what is announced
    Advert.for_server(config, host=, port=, tls=, live=) -> Advert  ... for a bound API
    live_records(status) -> dict                                   STATUS's TXT records
    RcanAdvertiser(advert, interfaces=)                            async context manager:
        register on enter, `update(advert)` re-announces a changed address or endpoint,
        `follow(provider, interval_s)` re-announces whatever `provider()` says now,
        unregister (goodbye packets) on exit
    RcanBrowser(interfaces=)                                       live view of RCAN robots
    browse(timeout_s, interfaces=) -> list[DiscoveredRobot]        one-shot discovery

Instance `<manufacturer>-<model>-<device-id>` (from the RURI); TXT per the profile: `ruri`,
`role` (lowest role that may command motion), `version`/`spec` (RCAN 1.2), `bridge=ros2`,
`distro`, `api`, `status_endpoint`, `model`, `name`, `caps`; and, from a running bridge,
STATUS's `state` and `telemetry_ts` (`live_records`). Tests bind zeroconf to 127.0.0.1
only and run inside a private network namespace (`scripts/netns`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections.abc import Callable, Mapping, Sequence
from types import TracebackType
from typing import Any

import ifaddr  # zeroconf's own dependency for interface addresses
import msgspec
from zeroconf import InterfaceChoice, IPVersion, ServiceStateChange, Zeroconf
from zeroconf.asyncio import AsyncServiceBrowser, AsyncServiceInfo, AsyncZeroconf

from rcan_rtps.config import RcanConfig
from rcan_rtps.governance import RolePolicy
from rcan_rtps.rcan import SPOKEN, Effect, Status, parse_ruri
from rcan_rtps.rcan.actions import names, specs

log = logging.getLogger(__name__)

SERVICE_TYPE = "_rcan._tcp.local."
RCAN_SPEC = "1.2"  # `version` and `spec`, as 1.2 clients read them
_RESOLVE_MS = 3000.0
_WILDCARDS = ("", "0.0.0.0")


class Advert(msgspec.Struct, frozen=True, kw_only=True):
    """What one robot announces. Two equal adverts announce the same thing."""

    instance: str
    port: int
    addresses: tuple[str, ...]
    txt: dict[str, str]

    @classmethod
    def from_config(cls, config: RcanConfig, *, api_url: str,
                    addresses: Sequence[str]) -> Advert:
        ruri = parse_ruri(config.robot.ruri)
        instance = f"{ruri.manufacturer}-{ruri.model}-{ruri.device_id}"
        url = api_url.rstrip("/")
        port = int(url.rsplit(":", 1)[1]) if url.count(":") >= 2 else (
            443 if url.startswith("https") else 80)
        return cls(instance=instance, port=port, addresses=tuple(addresses),
                   txt=txt_records(config, api_url=url))


    @classmethod
    def for_server(cls, config: RcanConfig, *, host: str, port: int,
                   tls: bool = False, live: Mapping[str, str] | None = None) -> Advert:
        """The advert of an API bound to `host`:`port`. A wildcard bind announces every
        interface address, and its `api` URL names the mDNS host `<instance>.local`, which
        resolves to exactly those; call again (or `follow`) to pick up address changes.
        `live`: what the robot's STATUS says now (`live_records`), announced with it."""
        addresses = addresses_for(host)
        wildcard = host in _WILDCARDS
        ruri = parse_ruri(config.robot.ruri)
        where = f"{ruri.manufacturer}-{ruri.model}-{ruri.device_id}.local" if wildcard else \
            addresses[0]
        scheme = "https" if tls else "http"
        advert = cls.from_config(config, api_url=f"{scheme}://{where}:{port}",
                                 addresses=addresses)
        if live:
            advert = msgspec.structs.replace(advert, txt={**advert.txt, **live})
        return advert


def live_records(status: Status) -> dict[str, str]:
    """The TXT records of a robot's STATUS (spec §3.1 flow 2, §5.1: a registry reads STATUS
    and the latest telemetry's time from the advert): its `state`, and the time of its newest
    telemetry message (Unix seconds) to the minute, none before the first. Coarse on purpose:
    a changed record is announced again to every listener (RFC 6762 §8.4), so a record that
    changed with every message would announce every robot of a fleet at each `follow` round;
    the state changes with what the robot does, the minute once a minute. The whole STATUS is
    at `status_endpoint`."""
    records = {"state": str(status.state)}
    age = status.ros.last_telemetry_age_s
    if age is not None:
        newest_s = status.timestamp_ms / 1000 - age
        records["telemetry_ts"] = str(int(newest_s // 60 * 60))
    return records


def addresses_for(host: str) -> list[str]:
    """IPv4 addresses to announce for an API bound to `host`: for a wildcard, every
    non-loopback interface address (loopback only when there is no other)."""
    if host in _WILDCARDS:
        found = sorted({str(ip.ip) for adapter in ifaddr.get_adapters() for ip in adapter.ips
                        if ip.is_IPv4 and not str(ip.ip).startswith("127.")})
        return found or ["127.0.0.1"]
    try:
        socket.inet_aton(host)
    except OSError:
        infos = socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_STREAM)
        return sorted({str(info[4][0]) for info in infos})
    return [host]


def txt_records(config: RcanConfig, *, api_url: str) -> dict[str, str]:
    ruri = parse_ruri(config.robot.ruri)
    roles = RolePolicy.from_config(config.bridge.rbac)
    # The role a client needs to command the robot: to move it, and to stop what it started.
    lowest = min(roles.required(s.name) for s in specs() if s.motion or s.effect is Effect.HALT)
    return {
        "ruri": config.robot.ruri,
        "role": lowest.name,
        "version": RCAN_SPEC,
        "spec": RCAN_SPEC,
        # Every protocol version spoken (the 1.2 dialect, and RCAN 3.x as the SDK writes it),
        # and the newest, under the name the node manifest gives it.
        "versions": ",".join(SPOKEN),
        "rcan_version": SPOKEN[-1],
        "bridge": "ros2",
        "distro": config.bridge.ros2.distro,
        "api": api_url,
        "status_endpoint": f"{api_url}/api/status",
        "model": ruri.model,
        "name": config.robot.name or f"{ruri.manufacturer}-{ruri.model}-{ruri.device_id}",
        "caps": ",".join(names()),
    }


def _interfaces(interfaces: Sequence[str] | None) -> Any:
    return InterfaceChoice.All if interfaces is None else list(interfaces)


def _service_info(advert: Advert) -> AsyncServiceInfo:
    return AsyncServiceInfo(
        SERVICE_TYPE, f"{advert.instance}.{SERVICE_TYPE}",
        port=advert.port, properties=advert.txt,
        server=f"{advert.instance}.local.",
        addresses=[socket.inet_aton(a) for a in advert.addresses],
    )


class RcanAdvertiser:
    """Registers the advert on start, re-announces changes, withdraws it on close."""

    def __init__(self, advert: Advert, *, interfaces: Sequence[str] | None = None) -> None:
        self.advert = advert
        self._interfaces = interfaces
        self._zc: AsyncZeroconf | None = None
        self._info: AsyncServiceInfo | None = None
        self._follower: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Registers the advert; returns once probing (about 1.5 s) is done."""
        self._zc = AsyncZeroconf(interfaces=_interfaces(self._interfaces),
                                 ip_version=IPVersion.V4Only)
        self._info = _service_info(self.advert)
        await (await self._zc.async_register_service(self._info))

    async def update(self, advert: Advert) -> bool:
        """Re-announce if anything changed (address, endpoint, TXT); True if it did."""
        if advert == self.advert:
            return False
        if self._zc is None or self._info is None:
            raise RuntimeError("RcanAdvertiser not started")
        info = _service_info(advert)
        if (advert.instance, advert.addresses) != (self.advert.instance, self.advert.addresses):
            # Withdraw first (goodbye packets): a cache-flush announcement alone leaves an old
            # address, or the old name, in browsers that heard it less than a second ago.
            await (await self._zc.async_unregister_service(self._info))
            await (await self._zc.async_register_service(info))
        else:
            await (await self._zc.async_update_service(info))
        self.advert, self._info = advert, info
        return True

    def follow(self, provider: Callable[[], Advert], interval_s: float = 5.0) -> None:
        """Every `interval_s`, re-announce what `provider()` says if it changed."""

        async def loop() -> None:
            while True:
                await asyncio.sleep(interval_s)
                try:
                    await self.update(provider())
                except Exception as exc:  # the next round tries again
                    log.warning("mDNS re-announcement failed (%s: %s)", type(exc).__name__, exc)
                    log.debug("mDNS re-announcement failure", exc_info=True)

        self._follower = asyncio.create_task(loop())

    async def close(self) -> None:
        """Withdraws the advert (goodbye packets); idempotent."""
        follower, self._follower = self._follower, None
        if follower is not None:
            follower.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await follower
        if self._zc is not None:
            if self._info is not None:
                with contextlib.suppress(Exception):  # goodbye packets are best effort
                    await (await self._zc.async_unregister_service(self._info))
            await self._zc.async_close()
            self._zc = None

    async def __aenter__(self) -> RcanAdvertiser:
        await self.start()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.close()


# -- discovery ------------------------------------------------------------------------------


class DiscoveredRobot(msgspec.Struct, frozen=True, kw_only=True):
    instance: str
    host: str | None
    port: int | None
    addresses: list[str]
    txt: dict[str, str]


def _robot(info: AsyncServiceInfo) -> DiscoveredRobot:
    txt = {k: v or "" for k, v in info.decoded_properties.items()}
    return DiscoveredRobot(
        instance=info.name.removesuffix("." + SERVICE_TYPE), host=info.server,
        port=info.port, addresses=sorted(info.parsed_addresses()), txt=txt,
    )


class RcanBrowser:
    """A live view of the RCAN robots announced on the chosen interfaces."""

    def __init__(self, *, interfaces: Sequence[str] | None = None) -> None:
        self._interfaces = interfaces
        self._zc: AsyncZeroconf | None = None
        self._browser: AsyncServiceBrowser | None = None
        self._names: set[str] = set()
        self._robots: dict[str, DiscoveredRobot] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._changed = asyncio.Event()

    def robots(self) -> list[DiscoveredRobot]:
        return sorted(self._robots.values(), key=lambda r: r.instance)

    async def start(self) -> None:
        self._zc = AsyncZeroconf(interfaces=_interfaces(self._interfaces),
                                 ip_version=IPVersion.V4Only)
        self._browser = AsyncServiceBrowser(self._zc.zeroconf, SERVICE_TYPE,
                                            handlers=[self._on_change])

    def _on_change(self, zeroconf: Zeroconf, service_type: str, name: str,
                   state_change: ServiceStateChange) -> None:
        if state_change is ServiceStateChange.Removed:
            self._names.discard(name)
            self._robots.pop(name, None)
            self._changed.set()
            return
        self._names.add(name)
        task = asyncio.create_task(self._resolve(name))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _resolve(self, name: str) -> None:
        assert self._zc is not None
        info = AsyncServiceInfo(SERVICE_TYPE, name)
        if await info.async_request(self._zc.zeroconf, _RESOLVE_MS) and name in self._names:
            self._robots[name] = _robot(info)
            self._changed.set()

    def _refresh_from_cache(self) -> None:
        """Pick up record changes (e.g. a new address) the browser reports no event for."""
        assert self._zc is not None
        for name in list(self._names):
            info = AsyncServiceInfo(SERVICE_TYPE, name)
            if info.load_from_cache(self._zc.zeroconf):
                robot = _robot(info)
                if self._robots.get(name) != robot:
                    self._robots[name] = robot
                    self._changed.set()

    async def wait_for(self, predicate: Callable[[list[DiscoveredRobot]], bool],
                       timeout_s: float, poll_s: float = 0.2) -> list[DiscoveredRobot]:
        """The robots once `predicate` holds for them; TimeoutError after `timeout_s`."""

        async def watch() -> list[DiscoveredRobot]:
            while True:
                self._refresh_from_cache()
                robots = self.robots()
                if predicate(robots):
                    return robots
                self._changed.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._changed.wait(), poll_s)

        return await asyncio.wait_for(watch(), timeout_s)

    async def settle(self) -> None:
        """Wait for the resolutions already started (each bounded by its own timeout)."""
        await asyncio.gather(*self._tasks, return_exceptions=True)

    async def close(self) -> None:
        """Idempotent."""
        browser, self._browser = self._browser, None
        if browser is not None:
            await browser.async_cancel()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._zc is not None:
            await self._zc.async_close()
            self._zc = None

    async def __aenter__(self) -> RcanBrowser:
        await self.start()
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None,
                        exc: BaseException | None, tb: TracebackType | None) -> None:
        await self.close()


async def browse(timeout_s: float = 3.0, *,
                 interfaces: Sequence[str] | None = None) -> list[DiscoveredRobot]:
    """Every RCAN robot that answered within `timeout_s`."""
    async with RcanBrowser(interfaces=interfaces) as browser:
        await asyncio.sleep(timeout_s)
        await browser.settle()
        return browser.robots()
