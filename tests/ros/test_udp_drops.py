"""ros.udp_drops: the kernel's count of datagrams dropped at given UDP sockets, and a node's
count at its DDS domain's sockets."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from dropping import flood, ports_of, small_buffers

from rcan_rtps.ros import udp_drops
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.udp_drops import dropped_at, made_between, udp_socket_inodes

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="the count is Linux's /proc")


@contextmanager
def receiver() -> Iterator[tuple[socket.socket, frozenset[str]]]:
    """A socket nobody reads, with the least receive buffer; and its inode."""
    before = udp_socket_inodes()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
        sock.bind(("127.0.0.1", 0))
        made = made_between(before, udp_socket_inodes())
        assert made is not None and len(made) == 1
        yield sock, made


def send(to: socket.socket, count: int = 30) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        for _ in range(count):
            sender.sendto(b"x" * 1000, to.getsockname())


def test_counts_what_a_full_receive_buffer_dropped() -> None:
    with receiver() as (sock, inodes):
        assert dropped_at(inodes) == 0
        send(sock)  # the buffer fills, the rest is dropped
        dropped = dropped_at(inodes)
        assert dropped is not None and dropped >= 20


CHILD = """
import socket, sys
receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
receiver.bind(("127.0.0.1", 0))
sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
for _ in range(30):
    sender.sendto(b"x" * 1000, receiver.getsockname())
print("dropped", flush=True)
sys.stdin.read()
"""


def test_drops_at_other_sockets_are_not_counted() -> None:
    with receiver() as (_quiet, inodes), \
            subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True) as child:
        assert child.stdout is not None and child.stdout.readline() == "dropped\n"
        assert _table_drops() >= 20  # the kernel counted them, for the child's socket
        assert dropped_at(inodes) == 0
        child.communicate("")


def _table_drops() -> int:
    with open("/proc/self/net/udp", encoding="ascii") as rows:
        return sum(int(row.split()[12]) for row in list(rows)[1:])


def test_a_socket_no_longer_there_makes_the_count_unknown() -> None:
    """A closed socket's drops are gone from the tables: not knowing them is not zero."""
    with receiver() as (_sock, inodes):
        pass
    assert dropped_at(inodes) is None
    assert dropped_at(frozenset()) is None


def test_a_table_that_cannot_be_read_makes_the_count_unknown(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Only a table that is not there (no IPv6) is left out: the IPv4 table unreadable (a
    directory stands for it here, as root reads any file) or in a format we do not know
    must not leave the IPv6 table's count standing for all (Cyclone's sockets are IPv4: a
    drop there would go unseen, and feedback() would not wait for its repair)."""
    with receiver() as (_sock, inodes):
        assert dropped_at(inodes) == 0
        monkeypatch.setattr(udp_drops, "_TABLES", ("/proc/self/net/udp",
                                                   str(tmp_path / "none")))
        assert dropped_at(inodes) == 0  # no such table: no IPv6
        monkeypatch.setattr(udp_drops, "_TABLES", (str(tmp_path), "/proc/self/net/udp6"))
        assert dropped_at(inodes) is None
        unknown = tmp_path / "udp"
        inode = next(iter(inodes))
        unknown.write_text(f"header\n 0: 0100007F:1 00000000:0 07 0:0 0:0 0 0 0 {inode}\n")
        monkeypatch.setattr(udp_drops, "_TABLES", (str(unknown), "/proc/self/net/udp6"))
        assert dropped_at(inodes) is None


def test_a_node_counts_the_drops_at_its_domain_s_sockets(
        domain_id: int, monkeypatch: pytest.MonkeyPatch) -> None:
    small_buffers(monkeypatch)
    with RosNode("dropping", domain_id=domain_id) as node, \
            RosNode("second", domain_id=domain_id) as second:
        assert ports_of(node), "Cyclone's sockets were not found"
        assert ports_of(second) == ports_of(node)  # one domain, one set of sockets
        before = node.udp_drops()
        assert before is not None
        with receiver() as (other, _inodes):  # a drop elsewhere in the process: not counted
            send(other)
            assert node.udp_drops() == before
        flood(node)
        after = node.udp_drops()
        assert after is not None and after > before
