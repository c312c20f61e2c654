"""ros.udp_drops: the kernel's count of datagrams dropped on this process's UDP sockets."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

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
