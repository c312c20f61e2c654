"""Signed tree heads (STH) of the audit log, RFC 6962/9162 style, and their sidecar file.

A tree head says: the first `tree_size` entries of the log have Merkle root `root_hash` (RFC 6962
hashing over the leaves, see `merkle`), at `timestamp_ms`; `sig` is base64 Ed25519, by the
log's key, over the canonical JSON (sorted keys, no whitespace) of the other three fields. The
leaf of entry `seq` is its line as written, without the newline (leaf index seq - 1).

The log appends one tree head per commit batch (after the batch's fsync) to `<log>.sth`, one
canonical JSON object a line, and hands it to the witness (`witness`), if one is configured.
The sidecar is not fsynced per batch (that would double the fsyncs): after a power loss its last
heads may be missing, and an incomplete last line is cut when the log is opened. It never names
more entries than are durable in the log, so a head larger than the log means the log lost
entries. The same lines are what a file witness appends and what `audit verify --witness`
reads.
"""

from __future__ import annotations

import base64
import errno
import logging
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from ._durable import full_fsync, write_all
from ._json import decode_as
from .log_tail import lines_forwards

log = logging.getLogger(__name__)


class TreeHead(msgspec.Struct, frozen=True, kw_only=True):
    tree_size: int
    root_hash: str  # lowercase hex of the 32-byte Merkle root
    timestamp_ms: int
    sig: str = ""

    def signed_bytes(self) -> bytes:
        return msgspec.json.encode({"root_hash": self.root_hash, "timestamp_ms": self.timestamp_ms,
                                    "tree_size": self.tree_size}, order="sorted")

    @property
    def root(self) -> bytes:
        return bytes.fromhex(self.root_hash)

    def line(self) -> bytes:
        return msgspec.json.encode(self, order="sorted") + b"\n"

    def describe(self) -> str:
        return f"tree head of size {self.tree_size} (timestamp_ms {self.timestamp_ms})"


def tree_head_path(log_path: Path) -> Path:
    return log_path.with_name(log_path.name + ".sth")


def public_key_path(log_path: Path) -> Path:
    """The PEM public key the log writes beside itself (what `audit verify` uses by default)."""
    return log_path.with_name(log_path.name + ".pub")


def sign_tree_head(key: Ed25519PrivateKey, size: int, root: bytes, ms: int) -> TreeHead:
    head = TreeHead(tree_size=size, root_hash=root.hex(), timestamp_ms=ms)
    sig = base64.b64encode(key.sign(head.signed_bytes())).decode()
    return msgspec.structs.replace(head, sig=sig)


def signature_ok(head: TreeHead, pubkey: Ed25519PublicKey) -> bool:
    try:
        sig = base64.b64decode(head.sig, validate=True)
        pubkey.verify(sig, head.signed_bytes())
    except (ValueError, InvalidSignature):
        return False
    return base64.b64encode(sig).decode() == head.sig


class BadTreeHead(msgspec.Struct, frozen=True):
    line_no: int  # 1-based, in its file
    problem: str


def parse_tree_heads(data: bytes) -> tuple[list[TreeHead | BadTreeHead], bytes]:
    """Every complete line of a tree-head file, parsed (a line that is not a well-formed,
    canonical tree head is a BadTreeHead), and an unterminated tail (b"" if none)."""
    out: list[TreeHead | BadTreeHead] = []
    lines = data.split(b"\n")
    for n, line in enumerate(lines[:-1], start=1):
        out.append(parse_tree_head(line, n))
    return out, lines[-1]


class HeadLines:
    """The heads of an open tree-head file up to byte `end`, parsed a line at a time as
    `parse_tree_heads` parses them (a file of a head per commit batch grows with the log: it
    is never held). Once iterated, `torn` is the length of its unterminated tail."""

    def __init__(self, fd: int, end: int) -> None:
        self._fd, self._end = fd, end
        self.torn = 0

    def __iter__(self) -> Iterator[tuple[int, TreeHead | BadTreeHead]]:
        """(line number from 1, the head or why not)."""
        tail = 0  # where the unterminated tail, if any, starts
        for n, (offset, line) in enumerate(lines_forwards(self._fd, 0, self._end), start=1):
            tail = offset + len(line) + 1
            yield n, parse_tree_head(line, n)
        self.torn = self._end - tail


def parse_tree_head(line: bytes, n: int) -> TreeHead | BadTreeHead:
    """Line `n` (1-based) of a tree-head file, without its newline: the head, or why not."""
    try:
        head = decode_as(line, TreeHead)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        return BadTreeHead(n, f"not a tree head ({exc})")
    if head.line() != line + b"\n":
        return BadTreeHead(n, "not in canonical form")
    if head.tree_size < 0 or len(head.root_hash) != 64 or head.root_hash != head.root_hash.lower():
        return BadTreeHead(n, "malformed size or root_hash")
    try:
        bytes.fromhex(head.root_hash)
    except ValueError:
        return BadTreeHead(n, "root_hash is not hex")
    return head


class TreeHeadFile:
    """The log's sidecar of tree heads, appended to by the log's writer (one at a time)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            # A FIFO there takes heads until its buffer is full, then blocks the log's writer
            # (and every governed command behind it): no heads rather than that.
            if not stat.S_ISREG(os.fstat(self._fd).st_mode):
                raise OSError(errno.EINVAL, "not a regular file", str(path))
            self._size = _cut_torn_tail(self._fd, path)
        except BaseException:
            os.close(self._fd)
            raise
        self._failing = False

    def append(self, head: TreeHead) -> bool:
        """Best effort: the log's entries are durable whatever happens here. A failed write
        is cut back (no torn line for the next head to follow), logged once until one works."""
        line = head.line()
        try:
            write_all(self._fd, line)
        except OSError as exc:
            try:
                os.ftruncate(self._fd, self._size)
            except OSError:
                log.exception("audit tree heads %s: cannot cut a failed write", self.path)
            if not self._failing:
                log.warning("audit tree head not written to %s: %s", self.path, exc)
            self._failing = True
            return False
        self._size += len(line)
        if self._failing:
            log.warning("audit tree heads written to %s again", self.path)
        self._failing = False
        return True

    def sync(self) -> None:
        try:
            full_fsync(self._fd)
        except OSError as exc:
            log.warning("audit tree heads %s not synced: %s", self.path, exc)

    def close(self) -> None:
        if self._fd >= 0:
            self.sync()
            os.close(self._fd)
            self._fd = -1


def _cut_torn_tail(fd: int, path: Path) -> int:
    """Cut an unterminated last line (a crash mid-append; the file is not fsynced per head).
    Read back a block at a time, each alone: a file without a newline in megabytes (not
    heads) is neither held nor read again with every block."""
    size = end = os.fstat(fd).st_size
    keep = 0
    while end > 0:
        start = max(0, end - 4096)
        cut = os.pread(fd, end - start, start).rfind(b"\n")
        if cut >= 0:
            keep = start + cut + 1
            break
        end = start
    if keep != size:
        log.warning("audit tree heads %s: cutting an incomplete last line (%d bytes)",
                    path, size - keep)
        os.ftruncate(fd, keep)
        full_fsync(fd)
    return keep
