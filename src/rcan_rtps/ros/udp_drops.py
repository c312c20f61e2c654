"""How many datagrams the kernel dropped on this process's UDP sockets (Linux).

A reliable DDS sample whose datagram is dropped at our socket (its receive buffer full on a
busy host) comes again only after its writer's next HEARTBEAT, and nothing the reader can
see through the DDS API says that a sample is still owed. Samples of *other* writers sent
after it (an action's status, a service's reply) then arrive first. The kernel counts each
drop per socket (`/proc/net/udp`, last column); a client that knows no drop happened since
it started waiting knows nothing can be owed (docs/design/zero-loss.md).
"""

from __future__ import annotations

import os

_TABLES = ("/proc/self/net/udp", "/proc/self/net/udp6")
_INODE, _DROPS = 9, 12  # columns of /proc/net/udp


def _socket_inodes() -> set[str] | None:
    """The inodes of this process's sockets, as /proc/net/udp writes them."""
    try:
        names = os.listdir("/proc/self/fd")
    except OSError:
        return None
    inodes = set()
    for name in names:
        try:
            target = os.readlink(f"/proc/self/fd/{name}")
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    return inodes


def socket_drops() -> int | None:
    """Datagrams dropped so far on this process's UDP sockets (IPv4 and IPv6); None where
    the kernel does not say (not Linux, no /proc) or not all of it: a table there but not
    readable, or in a format we do not know (only one not there, no IPv6, is left out)."""
    inodes = _socket_inodes()
    if inodes is None:
        return None
    total, tables = 0, 0
    for table in _TABLES:
        try:
            total += _table_drops(table, inodes)
        except FileNotFoundError:  # no IPv6
            continue
        except (OSError, ValueError):
            return None
        tables += 1
    return total if tables else None


def _table_drops(table: str, inodes: set[str]) -> int:
    total = 0
    with open(table, encoding="ascii") as rows:
        next(rows, None)  # the header
        for row in rows:
            fields = row.split()
            if len(fields) <= _DROPS:
                raise ValueError(f"{table}: a row of {len(fields)} fields")
            if fields[_INODE] in inodes:
                total += int(fields[_DROPS])
    return total
