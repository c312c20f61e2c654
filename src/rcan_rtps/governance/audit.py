"""§6 audit chain: JSON lines, SHA-256 links, Ed25519 signatures, durable group commit.

Each line is the canonical JSON (sorted keys, no whitespace, UTF-8) of one entry. `audit_id` is
"sha256:" + hex SHA-256 of the canonical entry without `audit_id` and `sig`; `prev_hash` is the
previous `audit_id` (the first links to GENESIS); `sig` is base64 Ed25519 over `audit_id`.
"""

from __future__ import annotations

import asyncio
import base64
import datetime as dt
import enum
import fcntl
import hashlib
import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from ._durable import fsync_dir, full_fsync, write_all
from .clock import Clock, SystemClock
from .errors import AuditError, AuditIntegrityError, AuditKeyError, AuditWriteError

GENESIS = "sha256:" + "0" * 64
log = logging.getLogger(__name__)
_UNSIGNED = ("audit_id", "sig")
_REQUIRED = ("seq", "audit_id", "prev_hash", "sig", "event", "timestamp_ms")


class AuditEvent(str, enum.Enum):
    COMMAND_DISPATCHED = "COMMAND_DISPATCHED"
    COMMAND_REJECTED = "COMMAND_REJECTED"
    PENDING_AUTH = "PENDING_AUTH"
    HITL_AUTHORIZED = "HITL_AUTHORIZED"
    HITL_DENIED = "HITL_DENIED"
    HITL_EXPIRED = "HITL_EXPIRED"
    ESTOP = "ESTOP"
    ESTOP_CLEARED = "ESTOP_CLEARED"
    NETWORK_LOSS_SAFE_STOP = "NETWORK_LOSS_SAFE_STOP"
    BRIDGE_STARTED = "BRIDGE_STARTED"
    BRIDGE_STOPPED = "BRIDGE_STOPPED"
    AUDIT_TAIL_RECOVERED = "AUDIT_TAIL_RECOVERED"


class AuditRecord(msgspec.Struct, kw_only=True, frozen=True):
    """What a caller states; the log adds seq, links, time, ids and the signature."""

    event: AuditEvent
    principal: str | None = None
    role: str | None = None
    message_id: str | None = None
    action_type: str | None = None
    params: dict[str, Any] | None = None
    applied: dict[str, Any] | None = None
    outcome: str | None = None
    deny_reason: str | None = None
    ai: dict[str, Any] | None = None
    ros2_topic: str | None = None
    pending_id: str | None = None


class AuditReceipt(msgspec.Struct, frozen=True):
    seq: int
    audit_id: str


class ChainHead(msgspec.Struct, frozen=True):
    """Where a verified chain ends."""

    count: int
    last_seq: int
    last_audit_id: str


def canonical(obj: Any) -> bytes:
    """Sorted keys, no whitespace, UTF-8; floats in shortest round-trip form."""
    return msgspec.json.encode(obj, order="sorted")


def entry_id(entry: dict[str, Any]) -> str:
    body = {k: v for k, v in entry.items() if k not in _UNSIGNED}
    return "sha256:" + hashlib.sha256(canonical(body)).hexdigest()


def iso_utc(ms: int) -> str:
    stamp = dt.datetime.fromtimestamp(ms // 1000, tz=dt.timezone.utc)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S") + f".{ms % 1000:03d}Z"


# -- keys -----------------------------------------------------------------------------------


def load_or_create_key(path: str | os.PathLike[str]) -> Ed25519PrivateKey:
    """The signing key; created (mode 0600) on first run, refused if others can read it."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return load_private_key(path)
    except OSError as exc:
        raise AuditKeyError(f"cannot create audit key {path}: {exc}") from exc
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    try:
        write_all(fd, pem)
        full_fsync(fd)
    finally:
        os.close(fd)
    fsync_dir(path.parent)
    return key


def load_private_key(path: str | os.PathLike[str]) -> Ed25519PrivateKey:
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise AuditKeyError(f"cannot read audit key {path}: {exc}") from exc
    # A signing key others can read lets them forge entries: refuse, as ssh does.
    if mode & 0o077:
        raise AuditKeyError(f"audit key {path} is readable by others (mode {mode & 0o777:o})")
    try:
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except (OSError, ValueError, TypeError) as exc:
        raise AuditKeyError(f"cannot load audit key {path}: {exc}") from exc
    if not isinstance(key, Ed25519PrivateKey):
        raise AuditKeyError(f"audit key {path} is not an Ed25519 key")
    return key


def public_key_pem(key: Ed25519PrivateKey) -> bytes:
    return key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )


def load_public_key(path: str | os.PathLike[str]) -> Ed25519PublicKey:
    try:
        key = serialization.load_pem_public_key(Path(path).read_bytes())
    except (OSError, ValueError) as exc:
        raise AuditKeyError(f"cannot load public key {path}: {exc}") from exc
    if not isinstance(key, Ed25519PublicKey):
        raise AuditKeyError(f"{path} is not an Ed25519 public key")
    return key


# -- verification ---------------------------------------------------------------------------


class _Scan(msgspec.Struct):
    head: ChainHead
    good_end: int  # byte offset just past the last complete, valid line
    torn: bytes  # an unterminated tail (a crash mid-append), or b""


def _lines(data: bytes) -> Iterator[tuple[int, bytes]]:
    start = 0
    while start < len(data):
        end = data.find(b"\n", start)
        if end < 0:
            return
        yield start, data[start:end]
        start = end + 1


def _check_line(line: bytes, seq: int, prev: str, pubkey: Ed25519PublicKey | None) -> str:
    """Verify one line as entry `seq` after `prev`; returns its audit_id or raises."""
    try:
        entry = msgspec.json.decode(line)
    except (msgspec.DecodeError, UnicodeDecodeError) as exc:
        raise AuditIntegrityError(seq, f"not JSON ({exc})") from exc
    if not isinstance(entry, dict) or not all(k in entry for k in _REQUIRED):
        raise AuditIntegrityError(seq, "not an audit entry")
    if canonical(entry) != line:
        raise AuditIntegrityError(seq, "not in canonical form")
    if entry["seq"] != seq:
        raise AuditIntegrityError(seq, f"found seq {entry['seq']!r} where {seq} belongs")
    if entry["prev_hash"] != prev:
        raise AuditIntegrityError(seq, "prev_hash does not link to the previous entry")
    audit_id = entry_id(entry)
    if entry["audit_id"] != audit_id:
        raise AuditIntegrityError(seq, "audit_id does not match the entry's content")
    sig = _sig_bytes(entry["sig"], seq)
    if pubkey is not None:
        try:
            pubkey.verify(sig, audit_id.encode())
        except InvalidSignature as exc:
            raise AuditIntegrityError(seq, "bad signature") from exc
    return audit_id


def _sig_bytes(text: Any, seq: int) -> bytes:
    """The signature, in its one canonical base64 spelling (padding bits included)."""
    try:
        sig = base64.b64decode(text, validate=True)
    except (ValueError, TypeError) as exc:
        raise AuditIntegrityError(seq, "sig is not base64") from exc
    if len(sig) != 64 or base64.b64encode(sig).decode() != text:
        raise AuditIntegrityError(seq, "sig is not a canonical Ed25519 signature")
    return sig


def _scan(data: bytes, pubkey: Ed25519PublicKey | None) -> _Scan:
    prev, seq, good_end = GENESIS, 0, 0
    for start, line in _lines(data):
        prev = _check_line(line, seq + 1, prev, pubkey)
        seq += 1
        good_end = start + len(line) + 1
    head = ChainHead(count=seq, last_seq=seq, last_audit_id=prev)
    return _Scan(head=head, good_end=good_end, torn=data[good_end:])


def verify(
    path: str | os.PathLike[str], pubkey: Ed25519PublicKey | None = None
) -> ChainHead:
    """Verify a whole audit file; raises AuditIntegrityError naming the first bad seq.

    Without `pubkey` only the hash chain is checked (anyone could have rebuilt it).
    """
    try:
        return verify_bytes(Path(path).read_bytes(), pubkey)
    except AuditIntegrityError as exc:
        raise AuditIntegrityError(exc.seq, exc.detail, path=str(path)) from exc


def verify_bytes(data: bytes, pubkey: Ed25519PublicKey | None = None) -> ChainHead:
    """`verify` on the content of an audit file."""
    scan = _scan(data, pubkey)
    if scan.torn:
        raise AuditIntegrityError(scan.head.last_seq + 1, "incomplete last line (torn tail)")
    return scan.head


# -- the log --------------------------------------------------------------------------------


def _write_durable(fd: int, data: bytes) -> None:
    write_all(fd, data)
    full_fsync(fd)


class AuditLog:
    """The append-only chain. `append` returns only once its entry is on disk (fsynced).

    With `group_commit`, appends that arrive while a write+fsync is running share the next one.
    """

    def __init__(self, fd: int, key: Ed25519PrivateKey, head: ChainHead, *, path: Path,
                 ruri: str | None, clock: Clock, group_commit: bool) -> None:
        self.path = path
        self._fd = fd
        self._key = key
        self._seq = head.last_seq
        self._prev = head.last_audit_id
        self._ruri = ruri
        self._clock = clock
        self._batch_limit = 0 if group_commit else 1
        self._queue: list[tuple[bytes, asyncio.Future[None]]] = []
        self._flusher: asyncio.Task[None] | None = None
        self._broken: BaseException | None = None
        # Told of every durable entry (e.g. metrics); a failing listener is logged, not raised.
        self.listeners: list[Callable[[AuditRecord], None]] = []

    @classmethod
    async def open(cls, path: str | os.PathLike[str], key_path: str | os.PathLike[str], *,
                   ruri: str | None = None, clock: Clock | None = None,
                   group_commit: bool = True) -> AuditLog:
        """Open (or create) the log, verify it whole, and cut a torn tail (audited).

        Any other break raises AuditIntegrityError: the bridge must not start on it.
        """
        key = load_or_create_key(key_path)
        fd, scan = await asyncio.to_thread(_open_and_scan, Path(path), key.public_key())
        log = cls(fd, key, scan.head, path=Path(path), ruri=ruri,
                  clock=clock or SystemClock(), group_commit=group_commit)
        if scan.torn:
            await log.append(AuditRecord(
                event=AuditEvent.AUDIT_TAIL_RECOVERED,
                params={"cut_bytes": len(scan.torn),
                        "cut_sha256": hashlib.sha256(scan.torn).hexdigest(),
                        "after_seq": scan.head.last_seq},
            ))
        return log

    @property
    def public_key(self) -> Ed25519PublicKey:
        return self._key.public_key()

    @property
    def healthy(self) -> bool:
        return self._broken is None and self._fd >= 0

    @property
    def head(self) -> ChainHead:
        return ChainHead(count=self._seq, last_seq=self._seq, last_audit_id=self._prev)

    async def append(self, record: AuditRecord) -> AuditReceipt:
        """Chain, sign and durably write one entry; returns once it is fsynced."""
        if not self.healthy:
            raise AuditWriteError(f"audit log {self.path} is not writable") from self._broken
        line, receipt = self._seal(record)
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._queue.append((line, done))
        if self._flusher is None or self._flusher.done():
            self._flusher = asyncio.create_task(self._flush())
        # A cancelled caller must not leave its entry half-acknowledged: the write goes on.
        await asyncio.shield(done)
        for listener in self.listeners:
            try:
                listener(record)
            except Exception:
                log.exception("audit listener failed")
        return receipt

    async def close(self) -> None:
        if self._flusher is not None:
            await asyncio.gather(self._flusher, return_exceptions=True)
        if self._fd >= 0:
            os.close(self._fd)  # closing also drops the flock
            self._fd = -1

    def _seal(self, record: AuditRecord) -> tuple[bytes, AuditReceipt]:
        """Assign seq and link synchronously, so the chain order is the call order."""
        ms = int(self._clock.time() * 1000)
        entry: dict[str, Any] = {
            k: v for k, v in msgspec.structs.asdict(record).items()
            if not (k in ("ai", "pending_id") and v is None)
        }
        entry.update(
            seq=self._seq + 1, prev_hash=self._prev, timestamp=iso_utc(ms), timestamp_ms=ms,
            ruri=self._ruri, bridge="ros2", event=record.event.value,
        )
        audit_id = entry_id(entry)
        entry["audit_id"] = audit_id
        entry["sig"] = base64.b64encode(self._key.sign(audit_id.encode())).decode()
        self._seq += 1
        self._prev = audit_id
        return canonical(entry) + b"\n", AuditReceipt(seq=self._seq, audit_id=audit_id)

    async def _flush(self) -> None:
        while self._queue:
            take = self._batch_limit or len(self._queue)
            batch, self._queue = self._queue[:take], self._queue[take:]
            try:
                await asyncio.to_thread(_write_durable, self._fd, b"".join(b for b, _ in batch))
            except OSError as exc:
                self._fail(batch + self._queue, exc)
                return
            for _, done in batch:
                done.set_result(None)

    def _fail(self, waiting: list[tuple[bytes, asyncio.Future[None]]], exc: OSError) -> None:
        # After a failed write the file's tail is unknown: refuse every further append.
        self._broken = exc
        self._queue = []
        for _, done in waiting:
            done.set_exception(AuditWriteError(f"audit write to {self.path} failed: {exc}"))


def _open_and_scan(path: Path, pubkey: Ed25519PublicKey) -> tuple[int, _Scan]:
    created = not path.exists()
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        _lock(fd, path)
        data = _read_all(fd)
        try:
            scan = _scan(data, pubkey)
        except AuditIntegrityError as exc:
            raise AuditIntegrityError(exc.seq, exc.detail + "; refusing to start",
                                      path=str(path)) from exc
        if scan.torn:
            os.ftruncate(fd, scan.good_end)
            full_fsync(fd)
        if created:
            fsync_dir(path.parent)
    except BaseException:
        os.close(fd)
        raise
    return fd, scan


def _lock(fd: int, path: Path) -> None:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError as exc:
        raise AuditError(f"audit log {path} is in use by another process") from exc


def _read_all(fd: int) -> bytes:
    os.lseek(fd, 0, os.SEEK_SET)
    chunks = []
    while chunk := os.read(fd, 1 << 20):
        chunks.append(chunk)
    return b"".join(chunks)
