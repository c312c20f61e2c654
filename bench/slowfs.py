"""A slow disk for the benchmarks: a FUSE passthrough filesystem whose flushes to "the device"
take `--fsync-ms` each.

    python bench/slowfs.py BACKING MOUNTPOINT [--fsync-ms 80]

Every file operation is passed to BACKING (a directory on a normal disk). `fsync` and
`fsyncdir` (what makes a write or a rename durable) first sleep `--fsync-ms`, then do the real
fsync, one at a time: the device serves one flush after another, like the SD card or eMMC of a
small robot computer. Writes land in the page cache as on any disk and cost nothing extra.
Runs in the foreground until the mount point is unmounted (`umount MOUNTPOINT`, as root).

Needs `fusepy` (ctypes bindings to libfuse 2) and the `libfuse2` library. These are tools of
the benchmark, never of the product: `bench/safety.py` installs them (`ensure_fuse_tools`),
fusepy into `.cache/bench-tools` (`pip install --target`), libfuse2 with apt-get.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

TOOLS = Path(__file__).resolve().parents[1] / ".cache" / "bench-tools"
sys.path.insert(0, str(TOOLS))
from fuse import FUSE, FuseOSError, Operations  # noqa: E402  (fusepy, from TOOLS)

STAT_KEYS = ("st_atime", "st_ctime", "st_gid", "st_mode", "st_mtime", "st_nlink", "st_size",
             "st_uid")


class SlowPassthrough(Operations):  # type: ignore[misc]
    def __init__(self, root: Path, fsync_s: float) -> None:
        self.root = root
        self.fsync_s = fsync_s
        self.device = threading.Lock()  # one flush at a time

    def _real(self, path: str) -> str:
        return str(self.root) + path

    def _flush_to_device(self, fd: int) -> None:
        with self.device:
            time.sleep(self.fsync_s)
            os.fsync(fd)

    # -- metadata ----------------------------------------------------------------------------
    def getattr(self, path: str, fh: int | None = None) -> dict[str, Any]:
        st = os.fstat(fh) if fh is not None else os.lstat(self._real(path))
        return {key: getattr(st, key) for key in STAT_KEYS}

    def access(self, path: str, amode: int) -> int:
        if not os.access(self._real(path), amode):
            raise FuseOSError(errno.EACCES)
        return 0

    def chmod(self, path: str, mode: int) -> int:
        os.chmod(self._real(path), mode)
        return 0

    def chown(self, path: str, uid: int, gid: int) -> int:
        os.chown(self._real(path), uid, gid)
        return 0

    def utimens(self, path: str, times: tuple[float, float] | None = None) -> int:
        os.utime(self._real(path), times)
        return 0

    def statfs(self, path: str) -> dict[str, int]:
        st = os.statvfs(self._real(path))
        return {key: getattr(st, key) for key in (
            "f_bavail", "f_bfree", "f_blocks", "f_bsize", "f_favail", "f_ffree", "f_files",
            "f_flag", "f_frsize", "f_namemax")}

    # -- directories ---------------------------------------------------------------------------
    def readdir(self, path: str, fh: int) -> list[str]:
        return [".", "..", *os.listdir(self._real(path))]

    def mkdir(self, path: str, mode: int) -> int:
        os.mkdir(self._real(path), mode)
        return 0

    def rmdir(self, path: str) -> int:
        os.rmdir(self._real(path))
        return 0

    def opendir(self, path: str) -> int:
        return os.open(self._real(path), os.O_RDONLY | os.O_DIRECTORY)

    def releasedir(self, path: str, fh: int) -> int:
        os.close(fh)
        return 0

    def fsyncdir(self, path: str, datasync: int, fh: int) -> int:
        self._flush_to_device(fh)
        return 0

    def rename(self, old: str, new: str) -> int:
        os.replace(self._real(old), self._real(new))
        return 0

    def unlink(self, path: str) -> int:
        os.unlink(self._real(path))
        return 0

    # -- files (the kernel gives every write its offset, O_APPEND included) ---------------------
    def create(self, path: str, mode: int, fi: Any = None) -> int:
        return os.open(self._real(path), os.O_RDWR | os.O_CREAT, mode)

    def open(self, path: str, flags: int) -> int:
        return os.open(self._real(path), flags & ~os.O_APPEND)

    def read(self, path: str, size: int, offset: int, fh: int) -> bytes:
        return os.pread(fh, size, offset)

    def write(self, path: str, data: bytes, offset: int, fh: int) -> int:
        return os.pwrite(fh, data, offset)

    def truncate(self, path: str, length: int, fh: int | None = None) -> int:
        if fh is not None:
            os.ftruncate(fh, length)
        else:
            os.truncate(self._real(path), length)
        return 0

    def flush(self, path: str, fh: int) -> int:
        return 0

    def fsync(self, path: str, datasync: int, fh: int) -> int:
        self._flush_to_device(fh)
        return 0

    def release(self, path: str, fh: int) -> int:
        os.close(fh)
        return 0


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("backing", type=Path)
    parser.add_argument("mountpoint", type=Path)
    parser.add_argument("--fsync-ms", type=float, default=80.0)
    args = parser.parse_args()
    FUSE(SlowPassthrough(args.backing.resolve(), args.fsync_ms / 1e3), str(args.mountpoint),
         foreground=True, nothreads=False)


if __name__ == "__main__":
    main()
