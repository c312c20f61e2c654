"""How many datagrams the kernel dropped at given UDP sockets of this process (Linux).

A reliable DDS sample whose datagram is dropped at our socket (its receive buffer full on a
busy host) comes again only after its writer's next HEARTBEAT, and nothing the reader can
see through the DDS API says that a sample is still owed. Samples of *other* writers sent
after it (an action's status, a service's reply) then arrive first. The kernel counts each
drop per socket (`/proc/net/udp`, last column); a client that knows no drop happened at its
DDS domain's sockets since it started waiting knows nothing can be owed
(docs/design/zero-loss.md).

The sockets are found once, when Cyclone makes them (`udp_socket_inodes` before and after),
because finding them means a look at every descriptor of the process (about 40 ms with 5,000
open sockets); counting their drops is one read of the tables.
"""

from __future__ import annotations

import os

_TABLES = ("/proc/self/net/udp", "/proc/self/net/udp6")
_INODE, _DROPS = 9, 12  # columns of /proc/net/udp


def udp_socket_inodes() -> frozenset[str] | None:
    """The inodes of this process's sockets now, as /proc/net/udp writes them; None where
    the kernel does not say (not Linux, no /proc)."""
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
    return frozenset(inodes)


def made_between(before: frozenset[str] | None,
                 after: frozenset[str] | None) -> frozenset[str] | None:
    """The sockets made between two looks (None when either look could not be had)."""
    return None if before is None or after is None else after - before


def dropped_at(sockets: frozenset[str]) -> int | None:
    """Datagrams dropped so far at these sockets (IPv4 and IPv6 tables); None when that is
    not known in full: no /proc, a table there but not readable or in a format we do not
    know (only one not there, no IPv6, is left out), or a socket in neither table."""
    total, found, tables = 0, 0, 0
    for table in _TABLES:
        try:
            drops, seen = _table_drops(table, sockets)
        except FileNotFoundError:  # no IPv6
            continue
        except (OSError, ValueError):
            return None
        total, found, tables = total + drops, found + seen, tables + 1
    return total if tables and sockets and found == len(sockets) else None


def _table_drops(table: str, sockets: frozenset[str]) -> tuple[int, int]:
    total = seen = 0
    with open(table, encoding="ascii") as rows:
        next(rows, None)  # the header
        for row in rows:
            fields = row.split()
            if len(fields) <= _DROPS:
                raise ValueError(f"{table}: a row of {len(fields)} fields")
            if fields[_INODE] in sockets:
                total, seen = total + int(fields[_DROPS]), seen + 1
    return total, seen
