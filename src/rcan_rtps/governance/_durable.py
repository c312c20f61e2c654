"""Small durable-file helpers: full fsync, atomic replace, private files."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import stat
from collections.abc import Iterator
from pathlib import Path


def full_fsync(fd: int) -> None:
    """fsync that reaches the platter: macOS needs F_FULLFSYNC, plain fsync elsewhere."""
    full = getattr(fcntl, "F_FULLFSYNC", None)
    if full is not None:
        try:
            fcntl.fcntl(fd, full)
            return
        except OSError:
            pass  # not supported by this filesystem: plain fsync is the best there is
    os.fsync(fd)


def fsync_dir(path: Path) -> None:
    """Make a directory entry (a created or renamed file) durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        written = os.write(fd, view)
        view = view[written:]


def not_regular_problem(path: str | os.PathLike[str]) -> str | None:
    """Why the file at `path` (links followed) cannot be one the bridge keeps its state in: it
    is there, and no regular file (a device, a FIFO, a directory). None when it is regular or
    not there (it is made); other errors are left to whoever opens it."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode):
        return None
    return f"{os.fspath(path)} is not a regular file"


def atomic_write(path: Path, data: bytes, mode: int = 0o600) -> None:
    """Write-then-rename, so a reader sees the old content or the new one, never half. A
    device at `path` is never replaced (run as root, `estop_state_path: /dev/null` had the
    first e-stop put a file in the place of the system's /dev/null)."""
    if _is_device(path):
        raise PermissionError(errno.EPERM, "a device is never replaced", os.fspath(path))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    # Made afresh, never opened as found: a FIFO there (its name is no secret) would hold
    # this thread — and the e-stop's persistence, or the audit log's writer — for a reader
    # that never comes, and a link there would have the write land in its target.
    with contextlib.suppress(FileNotFoundError):
        os.unlink(tmp)  # (a leftover of a write a crash cut, or what someone put there)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, mode)
    try:
        try:
            write_all(fd, data)
            full_fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError:
        with contextlib.suppress(OSError):  # a full disk must not keep a half-written copy
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def _is_device(path: Path) -> bool:
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return False
    return stat.S_ISCHR(mode) or stat.S_ISBLK(mode)


@contextlib.contextmanager
def regular_file(path: Path) -> Iterator[tuple[int, os.stat_result]]:
    """An open descriptor of `path` and its stat; ValueError unless it is a regular file. Opened
    without blocking: a FIFO's open would wait for a writer that never comes."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{path} is not a regular file")
        yield fd, info
    finally:
        os.close(fd)


def regular_stat(path: Path) -> os.stat_result:
    """The stat of the regular file at `path`, judged on the file opened (without blocking);
    ValueError unless it is one, OSError if it cannot be opened."""
    with regular_file(path) as (_, info):
        return info


def foreign_owner_problem(path: Path, info: os.stat_result) -> str | None:
    """Why a key file is not the bridge's to trust or hold: neither the user it runs as nor
    root owns it. Its owner may rewrite it (chmod it first) and read it, whatever its mode
    says — the mode checks alone let another user's 0644 key set be trusted, and their
    0600 private key be used (ssh's StrictModes: owned by the user or root)."""
    mine = os.geteuid()
    if info.st_uid in (mine, 0):
        return None
    return (f"{path} is owned by uid {info.st_uid}, neither this user ({mine}) nor root: "
            "its owner can rewrite or read it whatever its mode (chown it)")


def read_small(path: Path, limit: int) -> bytes:
    """A small file's bytes (a checkpoint, a start point). Raises FileNotFoundError if there is
    none, ValueError if it is no regular file or holds more than `limit` bytes: a FIFO put in
    its place would block the reader (a start, with its e-stop) for a writer that never comes,
    and a device or a huge file would be read into memory before anything could refuse it."""
    return read_small_with_stat(path, limit)[0]


# Group or others may write it: whoever can, can put their own key in (ssh's StrictModes rule).
WRITABLE_BY_OTHERS = 0o022


def writable_directory_problem(path: Path) -> str | None:
    """Why a file the bridge trusts keys from may be replaced by others: a directory it is in
    (the named path's and, through links, the file's) may be written by its group or others
    and is not sticky, or is owned by neither this user nor root — whoever may write the
    directory renames a file of their own over it, whatever the file's own mode (ssh's
    StrictModes walks the directories too)."""
    mine = os.geteuid()
    named = Path(os.path.abspath(path)).parents
    resolved = Path(os.path.realpath(path)).parents
    for directory in dict.fromkeys([*named, *resolved]):
        try:
            info = os.stat(directory)
        except OSError:
            continue  # (the file's own open says what is wrong)
        if info.st_uid not in (mine, 0):
            return (f"{directory} is owned by uid {info.st_uid}, neither this user ({mine}) "
                    f"nor root: its owner can replace {path} (chown it)")
        if info.st_mode & WRITABLE_BY_OTHERS and not info.st_mode & stat.S_ISVTX:
            return (f"{directory} may be written by others (mode {info.st_mode & 0o7777:o}): "
                    f"whoever can write it can replace {path} with their own (chmod go-w, "
                    "or +t)")
    return None


def read_trusted(path: Path, limit: int) -> bytes:
    """`read_small` of a file the bridge trusts keys from (a JWT issuer's key or key set, a
    principal's signing key): ValueError if its group or others may write it — they could put
    their own key there and mint tokens or sign commands of any role."""
    data, info = read_small_with_stat(path, limit)
    mode = info.st_mode
    owner = foreign_owner_problem(path, info)
    if owner is not None:
        raise ValueError(owner)
    if mode & WRITABLE_BY_OTHERS:
        raise ValueError(f"{path} may be written by others (mode {mode & 0o777:o}): whoever "
                         "can write it can put their own key in (chmod go-w)")
    directory = writable_directory_problem(path)
    if directory is not None:
        raise ValueError(directory)
    return data


def read_small_with_stat(path: Path, limit: int) -> tuple[bytes, os.stat_result]:
    """`read_small`, and the stat of the very file read (a private key's permissions and owner
    are judged on it, not on whatever a stat before found at its name)."""
    with regular_file(path) as (fd, info):
        if info.st_size > limit:
            raise ValueError(f"{path} is larger than {limit} bytes ({info.st_size})")
        # (one byte more than it holds: a file grown meanwhile is seen, never read on)
        data = os.pread(fd, info.st_size + 1, 0)
    if len(data) > info.st_size:
        raise ValueError(f"{path} is being written")
    return data, info
