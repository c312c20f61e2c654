"""Making the kernel drop datagrams at a node's DDS sockets, as it does on a busy host whose
receive buffers are full (docs/design/zero-loss.md)."""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from typing import Any

import pytest

from rcan_rtps.ros.participant import RosNode

# A domain whose sockets' receive buffers hold about two datagrams (put in CYCLONEDDS_URI
# before the domain's first node is made: the first node of a domain fixes its config).
SMALL_BUFFERS = '<Internal><SocketReceiveBufferSize min="{size}" max="{size}"/></Internal>'


def small_buffers(monkeypatch: pytest.MonkeyPatch, size: str = "3kB") -> None:
    monkeypatch.setenv("CYCLONEDDS_URI", SMALL_BUFFERS.format(size=size))


def _udp_rows(sockets: frozenset[str], pid: int | str = "self") -> list[list[str]]:
    """The kernel's UDP table rows (IPv4) of these sockets (inodes)."""
    with open(f"/proc/{pid}/net/udp", encoding="ascii") as rows:
        return [fields for row in list(rows)[1:] if (fields := row.split())[9] in sockets]


def ports_of(node: RosNode) -> list[int]:
    """The UDP ports of the node's DDS sockets (the kernel's table, by their inodes)."""
    return [int(fields[1].split(":")[1], 16) for fields in _udp_rows(node._sockets or frozenset())]


def flood(node: RosNode, size: int = 30_000, batches: int = 200) -> int:
    """Junk datagrams at each of the node's DDS sockets (Cyclone drops what is not RTPS),
    batch after batch until the kernel has dropped some there (with small buffers, soon:
    Cyclone's receive thread reads quickly, so one batch is not always enough). Returns how
    many it dropped."""
    return _flood(lambda: ports_of(node), node.udp_drops, size, batches)


def flood_process(pid: int, size: int = 30_000, batches: int = 200) -> int:
    """`flood`, at every UDP socket of another process (a CLI command's DDS sockets: it
    makes no others), whose domain has small buffers (`SMALL_BUFFERS` in its environment)."""
    sockets = frozenset(os.readlink(f"/proc/{pid}/fd/{fd}")[8:-1]
                        for fd in os.listdir(f"/proc/{pid}/fd")
                        if os.readlink(f"/proc/{pid}/fd/{fd}").startswith("socket:["))
    rows = _udp_rows(sockets, pid)
    assert rows, f"process {pid} has no UDP sockets"
    mine = frozenset(fields[9] for fields in rows)
    return _flood(lambda: [int(fields[1].split(":")[1], 16) for fields in rows],
                  lambda: sum(int(fields[12]) for fields in _udp_rows(mine, pid)), size, batches)


def _flood(ports: Callable[[], list[int]], drops: Callable[[], int | None], size: int,
           batches: int) -> int:
    before = drops()
    assert before is not None, "the kernel's drop counts are needed (Linux /proc)"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        for _ in range(batches):
            for port in ports():
                for _ in range(50):
                    sender.sendto(b"\0" * size, ("127.0.0.1", port))
            now = drops()
            if now is not None and now > before:
                return now - before
    raise AssertionError(f"{batches} batches of junk and no datagram dropped at the sockets")


class DeafCapture:
    """A node's packet capture (rtps_capture.py) in which no HEARTBEAT addressed to one of
    our readers ever shows, as when our socket dropped each Fast DDS writer's announcement:
    clients then wait for it and make their readers again (handshake.hear_announcements).
    Everything else is the real capture's. Install with `node.identities = DeafCapture(...)`."""

    def __init__(self, real: Any) -> None:
        assert real is not None, "the packet capture is needed (Linux, RCAN_RTPS_RPC_IDENTITY)"
        self._real = real

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)

    def heard_heartbeat(self, writer_guid: bytes, reader_guid: bytes, since: int = 0) -> bool:
        return False
