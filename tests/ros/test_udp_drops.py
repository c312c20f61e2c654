"""ros.udp_drops: the kernel's count of datagrams dropped on this process's UDP sockets."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from rcan_rtps.ros import udp_drops
from rcan_rtps.ros.udp_drops import socket_drops

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="the count is Linux's /proc")


def test_counts_what_a_full_receive_buffer_dropped() -> None:
    before = socket_drops()
    assert before is not None
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as receiver, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        receiver.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)  # the kernel's least
        receiver.bind(("127.0.0.1", 0))
        for _ in range(30):  # nobody reads: the buffer fills, the rest is dropped
            sender.sendto(b"x" * 1000, receiver.getsockname())
        during = socket_drops()
    assert during is not None and during - before >= 20


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


def test_another_process_s_drops_are_not_counted() -> None:
    before = socket_drops()
    with subprocess.Popen([sys.executable, "-c", CHILD], stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, text=True) as child:
        assert child.stdout is not None and child.stdout.readline() == "dropped\n"
        assert _table_drops() >= 20  # the kernel counted them, for the child's socket
        assert socket_drops() == before
        child.communicate("")


def _table_drops() -> int:
    with open("/proc/self/net/udp", encoding="ascii") as rows:
        return sum(int(row.split()[12]) for row in list(rows)[1:])


def test_a_table_that_cannot_be_read_makes_the_count_unknown(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Only a table that is not there (no IPv6) is left out: the IPv4 table unreadable (a
    directory stands for it here, as root reads any file) or in a format we do not know
    must not leave the IPv6 table's count standing for all (Cyclone's sockets are IPv4: a
    drop there would go unseen, and feedback() would not wait for its repair)."""
    assert socket_drops() is not None
    monkeypatch.setattr(udp_drops, "_TABLES", ("/proc/self/net/udp", str(tmp_path / "none")))
    assert socket_drops() is not None  # no such table: no IPv6
    monkeypatch.setattr(udp_drops, "_TABLES", (str(tmp_path), "/proc/self/net/udp6"))
    assert socket_drops() is None
    unknown = tmp_path / "udp"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as ours:
        ours.bind(("127.0.0.1", 0))
        inode = os.fstat(ours.fileno()).st_ino
        unknown.write_text(f"header\n 0: 0100007F:1 00000000:0 07 0:0 0:0 0 0 0 {inode}\n")
        monkeypatch.setattr(udp_drops, "_TABLES", (str(unknown), "/proc/self/net/udp6"))
        assert socket_drops() is None
