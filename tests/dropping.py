"""Making the kernel drop datagrams at a node's DDS sockets, as it does on a busy host whose
receive buffers are full (docs/design/zero-loss.md)."""

from __future__ import annotations

import socket
from typing import Any

import pytest

from rcan_rtps.ros.participant import RosNode

# A domain whose sockets' receive buffers hold about two datagrams (put in CYCLONEDDS_URI
# before the domain's first node is made: the first node of a domain fixes its config).
SMALL_BUFFERS = '<Internal><SocketReceiveBufferSize min="{size}" max="{size}"/></Internal>'


def small_buffers(monkeypatch: pytest.MonkeyPatch, size: str = "3kB") -> None:
    monkeypatch.setenv("CYCLONEDDS_URI", SMALL_BUFFERS.format(size=size))


def ports_of(node: RosNode) -> list[int]:
    """The UDP ports of the node's DDS sockets (the kernel's table, by their inodes)."""
    sockets = node._sockets or frozenset()
    ports = []
    with open("/proc/self/net/udp", encoding="ascii") as rows:
        for row in list(rows)[1:]:
            fields = row.split()
            if fields[9] in sockets:
                ports.append(int(fields[1].split(":")[1], 16))
    return ports


def flood(node: RosNode, size: int = 30_000, batches: int = 200) -> int:
    """Junk datagrams at each of the node's DDS sockets (Cyclone drops what is not RTPS),
    batch after batch until the kernel has dropped some there (with small buffers, soon:
    Cyclone's receive thread reads quickly, so one batch is not always enough). Returns how
    many it dropped."""
    before = node.udp_drops()
    assert before is not None, "the kernel's drop counts are needed (Linux /proc)"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        for _ in range(batches):
            for port in ports_of(node):
                for _ in range(50):
                    sender.sendto(b"\0" * size, ("127.0.0.1", port))
            now = node.udp_drops()
            if now is not None and now > before:
                return now - before
    raise AssertionError(f"{batches} batches of junk and no datagram dropped at the node's sockets")


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
