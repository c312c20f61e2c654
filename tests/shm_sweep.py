"""Fast DDS shared-memory segments the suite's rclpy peers left behind.

An rclpy node on rmw_fastrtps maps its shared-memory transport's port segments from
/dev/shm (`fastrtps_<hex>`, `fastdds_<hex>`, each with an `_el` lock file, about half a
MiB). A peer the tests kill on purpose (mid-call, mid-goal, on a signal) never unlinks its
own, so every suite run left a few hundred on the machine — RAM of a tmpfs, on the robot
computer CI runs on. After a run, a segment made during it that no live process holds
(open or mapped) is removed; one a process still uses is never touched.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

SHM = Path("/dev/shm")
SEGMENT = re.compile(r"^fast(rtps|dds)_[0-9a-f]+(_el)?$")


def segments(shm: Path = SHM) -> set[str]:
    """Names of the Fast DDS segments (and lock files) in `shm` now."""
    try:
        return {p.name for p in shm.iterdir() if SEGMENT.match(p.name)}
    except OSError:
        return set()


def in_use(shm: Path = SHM) -> set[str]:
    """Names under `shm` that some process has open or mapped (what /proc lets us see)."""
    held: set[str] = set()
    prefix = f"{shm}/"
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            held.update(p[len(prefix):] for p in _paths_of(proc) if p.startswith(prefix))
    return held


def _paths_of(proc: Path) -> list[str]:
    """The files a process has open and mapped (empty if it is gone or not ours to read)."""
    paths = []
    try:
        fds = list((proc / "fd").iterdir())
    except OSError:
        fds = []
    for fd in fds:
        try:  # an fd may close meanwhile (the listing's own, for one)
            paths.append(os.readlink(fd).removesuffix(" (deleted)"))
        except OSError:
            continue
    try:
        maps = (proc / "maps").read_text().splitlines()
    except OSError:
        maps = []
    for line in maps:
        fields = line.split(maxsplit=5)
        if len(fields) == 6:
            paths.append(fields[5].removesuffix(" (deleted)"))
    return paths


def sweep(before: set[str], shm: Path = SHM) -> list[str]:
    """Removes the segments made since `before` that no process holds; returns their names."""
    made = segments(shm) - before
    if not made:
        return []
    held = in_use(shm)
    # A lock file goes with its segment: kept while the segment is held.
    stale = [n for n in sorted(made) if n not in held and n.removesuffix("_el") not in held]
    for name in stale:
        try:
            (shm / name).unlink()
        except OSError:
            continue
    return stale
