"""§6 audit chain: JSON lines, SHA-256 links, Ed25519 signatures, durable group commit.

Each line is the canonical JSON (sorted keys, no whitespace, UTF-8) of one entry. `audit_id` is
"sha256:" + hex SHA-256 of the canonical entry without `audit_id` and `sig`; `prev_hash` is the
previous `audit_id` (the first links to GENESIS); `sig` is base64 Ed25519 over `audit_id`.

Writes run on the loop when the disk is fast (see INLINE_FSYNC_S), else on the log's own thread
(never the default executor, which costly reads may fill).
A signed checkpoint beside the log records the last verified entry, so opening the log checks
only what was appended after it: start-up time does not grow with the log. `verify` and
`rcan-rtps audit verify` still check the whole chain.
"""

from __future__ import annotations

import asyncio
import base64
import concurrent.futures
import datetime as dt
import enum
import fcntl
import functools
import hashlib
import logging
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from ._durable import atomic_write, fsync_dir, full_fsync, write_all
from .clock import Clock, SystemClock
from .errors import AuditError, AuditIntegrityError, AuditKeyError, AuditWriteError

GENESIS = "sha256:" + "0" * 64
log = logging.getLogger(__name__)
_UNSIGNED = ("audit_id", "sig")
_REQUIRED = ("seq", "audit_id", "prev_hash", "sig", "event", "timestamp_ms")
CHECKPOINT_EVERY = 1000  # entries between checkpoints: bounds what a start after a crash re-checks
# When the disk is fast (smoothed write+fsync below INLINE_FSYNC_S) the loop writes: an idle
# log's append at once (none in the last INLINE_GAP_S), a burst's entries together one loop
# turn after the turn the first was sealed in (group commit; the turn held back lets the next
# turn's entries share the fsync, about twice as many each, unless a stop is waiting): thread
# hand-offs cost more CPU than such an fsync blocks. Otherwise the writer thread does it, with
# group commit too: a slow disk (an SD card) never blocks the event loop.
INLINE_FSYNC_S = 0.001
INLINE_GAP_S = 0.001


class AuditEvent(str, enum.Enum):
    COMMAND_DISPATCHED = "COMMAND_DISPATCHED"
    COMMAND_REJECTED = "COMMAND_REJECTED"
    COMMAND_FAILED = "COMMAND_FAILED"  # written after a write-ahead entry whose send failed
    PENDING_AUTH = "PENDING_AUTH"
    HITL_APPROVAL = "HITL_APPROVAL"  # one of several approvals a held command needs
    HITL_AUTHORIZED = "HITL_AUTHORIZED"
    HITL_DENIED = "HITL_DENIED"
    HITL_WITHDRAWN = "HITL_WITHDRAWN"  # taken back by its issuer (or an approver)
    HITL_EXPIRED = "HITL_EXPIRED"
    ESTOP = "ESTOP"
    ESTOP_CLEARED = "ESTOP_CLEARED"
    NETWORK_LOSS_SAFE_STOP = "NETWORK_LOSS_SAFE_STOP"
    GOAL_FINISHED = "GOAL_FINISHED"  # a goal the bridge sent ended; `outcome` says how
    STREAM_ENDED = "STREAM_ENDED"  # a velocity stream stopped sending (params.reason says why)
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
    # The HiTL reviews of a held command (each approver, decision and reason), in order.
    approvals: list[dict[str, Any]] | None = None


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
    return _iso_second(ms // 1000) + f".{ms % 1000:03d}Z"


@functools.lru_cache(maxsize=4)
def _iso_second(second: int) -> str:
    # Cached: entries come many to a second, and formatting is a visible part of sealing one.
    return dt.datetime.fromtimestamp(second, tz=dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")


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
    try:
        write_all(fd, _ed25519_pkcs8_pem(key))
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
        pem = path.read_bytes()
        key = _ed25519_pkcs8(pem) or _load_pem(pem)
    except (OSError, ValueError, TypeError) as exc:
        raise AuditKeyError(f"cannot load audit key {path}: {exc}") from exc
    if not isinstance(key, Ed25519PrivateKey):
        raise AuditKeyError(f"audit key {path} is not an Ed25519 key")
    return key


# The unencrypted PKCS#8 DER of an Ed25519 key (RFC 8410) is this prefix and the 32-byte seed.
_PKCS8_ED25519 = bytes.fromhex("302e020100300506032b657004220420")
_PEM_HEAD, _PEM_TAIL = b"-----BEGIN PRIVATE KEY-----", b"-----END PRIVATE KEY-----"


def _ed25519_pkcs8_pem(key: Ed25519PrivateKey) -> bytes:
    """The unencrypted PKCS#8 PEM of `key`, the bytes `cryptography`'s PEM writer makes. Made
    here: that writer's module imports every key type (~1 MB a first start would keep)."""
    der = base64.b64encode(_PKCS8_ED25519 + key.private_bytes_raw())  # 64 chars: one line
    return b"\n".join((_PEM_HEAD, der, _PEM_TAIL, b""))


def _ed25519_pkcs8(pem: bytes) -> Ed25519PrivateKey | None:
    """The key of a PEM that is exactly an Ed25519 PKCS#8 key (what this bridge writes), else
    None. Parsed here: `cryptography`'s PEM loading imports every key type (~1 MB)."""
    text = pem.strip()
    if not (text.startswith(_PEM_HEAD) and text.endswith(_PEM_TAIL)):
        return None
    try:
        der = base64.b64decode(b"".join(text[len(_PEM_HEAD):-len(_PEM_TAIL)].split()),
                               validate=True)
    except ValueError:
        return None
    if len(der) != len(_PKCS8_ED25519) + 32 or not der.startswith(_PKCS8_ED25519):
        return None
    return Ed25519PrivateKey.from_private_bytes(der[len(_PKCS8_ED25519):])


def _load_pem(pem: bytes) -> object:
    from cryptography.hazmat.primitives import serialization

    return serialization.load_pem_private_key(pem, password=None)


def public_key_pem(key: Ed25519PrivateKey) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )


def load_public_key(path: str | os.PathLike[str]) -> Ed25519PublicKey:
    from cryptography.hazmat.primitives import serialization

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
    last_start: int = 0  # byte offset of the last valid line
    last_span: tuple[int, int] = (0, 0)  # (start, end) of the last valid line in the file


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


def _scan(data: bytes, pubkey: Ed25519PublicKey | None, *, seq: int = 0,
          prev: str = GENESIS) -> _Scan:
    """Verify `data` as the entries after `seq` (whose id is `prev`)."""
    good_end = last_start = 0
    for start, line in _lines(data):
        prev = _check_line(line, seq + 1, prev, pubkey)
        seq += 1
        good_end, last_start = start + len(line) + 1, start
    head = ChainHead(count=seq, last_seq=seq, last_audit_id=prev)
    return _Scan(head=head, good_end=good_end, torn=data[good_end:], last_start=last_start)


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


# -- checkpoints ----------------------------------------------------------------------------


class Checkpoint(msgspec.Struct, frozen=True, kw_only=True):
    """The last verified entry: its seq, id and byte span, signed with the log's key."""

    seq: int
    audit_id: str
    start: int  # byte offset of the entry's line
    end: int  # just past its newline: where verification resumes
    sig: str = ""

    def signed_bytes(self) -> bytes:
        return canonical({"seq": self.seq, "audit_id": self.audit_id,
                          "start": self.start, "end": self.end})


def checkpoint_path(log_path: Path) -> Path:
    return log_path.with_name(log_path.name + ".checkpoint")


def _write_checkpoint(path: Path, key: Ed25519PrivateKey, cp: Checkpoint) -> None:
    sig = base64.b64encode(key.sign(cp.signed_bytes())).decode()
    atomic_write(path, msgspec.json.encode(msgspec.structs.replace(cp, sig=sig)))


def _read_checkpoint(path: Path, pubkey: Ed25519PublicKey) -> Checkpoint | None:
    """A checkpoint this key signed, or None (missing, unreadable, or not ours)."""
    try:
        cp = msgspec.json.decode(path.read_bytes(), type=Checkpoint)
        pubkey.verify(base64.b64decode(cp.sig, validate=True), cp.signed_bytes())
    except FileNotFoundError:
        return None
    except (OSError, ValueError, msgspec.DecodeError, InvalidSignature):
        log.warning("audit checkpoint %s unusable: verifying the whole log", path)
        return None
    return cp


def _resume_point(fd: int, cp: Checkpoint) -> tuple[int, str, int] | None:
    """(seq, audit_id, offset) to verify from, if the checkpointed line is still there."""
    size = os.fstat(fd).st_size
    if not 0 <= cp.start < cp.end <= size:
        return None
    line = os.pread(fd, cp.end - cp.start, cp.start)
    if not line.endswith(b"\n"):
        return None
    try:
        entry = msgspec.json.decode(line[:-1])
    except msgspec.DecodeError:
        return None
    if not isinstance(entry, dict) or entry.get("seq") != cp.seq:
        return None
    if entry.get("audit_id") != cp.audit_id or entry_id(entry) != cp.audit_id:
        return None
    return cp.seq, cp.audit_id, cp.end


# -- the log --------------------------------------------------------------------------------


def _write_durable(fd: int, data: bytes) -> float:
    """Write and fsync; returns how long that took (seconds)."""
    started = time.perf_counter()
    write_all(fd, data)
    full_fsync(fd)
    return time.perf_counter() - started


_Queued = tuple[bytes, AuditReceipt, "asyncio.Future[None]"]  # a sealed line awaiting its fsync


class AuditLog:
    """The append-only chain. `append` returns only once its entry is on disk (fsynced).

    With `group_commit`, appends of two loop turns, or that arrive while the writer thread's
    write+fsync is running, share the next one.
    """

    def __init__(self, fd: int, key: Ed25519PrivateKey, head: ChainHead, *, path: Path,
                 ruri: str | None, clock: Clock, group_commit: bool, size: int,
                 writer: concurrent.futures.ThreadPoolExecutor) -> None:
        self.path = path
        self._fd = fd
        self._key = key
        self._seq = head.last_seq
        self._prev = head.last_audit_id
        self._ruri = ruri
        self._clock = clock
        self._batch_limit = 0 if group_commit else 1
        self._queue: list[_Queued] = []  # for the writer thread
        self._loop_batch: list[_Queued] = []  # for the group commit on the loop
        self._urgent = False  # the loop batch holds a stop: commit it without holding a turn
        self._flusher: asyncio.Task[None] | None = None
        self._broken: BaseException | None = None
        self._writer = writer  # one thread: writes and checkpoints in order, apart from reads
        self._size = size  # bytes durably in the file
        self._last_span = (max(0, size - 1), size)
        self._durable_seq, self._durable_id = head.last_seq, head.last_audit_id
        self._checkpointed_seq = -1  # none written by this process yet
        self._fsync_s = 0.0  # smoothed write+fsync time
        self._checkpointing: asyncio.Task[None] | None = None
        self._last_write_end = 0.0
        # Told of every durable entry (e.g. metrics); a failing listener is logged, not raised.
        self.listeners: list[Callable[[AuditRecord, AuditReceipt], None]] = []
        self._told: list[tuple[AuditRecord, AuditReceipt]] = []  # durable, listeners not told

    @classmethod
    async def open(cls, path: str | os.PathLike[str], key_path: str | os.PathLike[str], *,
                   ruri: str | None = None, clock: Clock | None = None,
                   group_commit: bool = True) -> AuditLog:
        """Open (or create) the log, verify what the checkpoint does not cover, cut a torn tail.

        A torn tail is cut and audited. Any other break raises AuditIntegrityError: the bridge
        must not start on it. Missing directories are created (mode 0700).
        """
        path = Path(path)
        writer = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="rcan-audit")
        try:
            await asyncio.get_running_loop().run_in_executor(writer, _make_dirs, path,
                                                             Path(key_path))
            key = load_or_create_key(key_path)
            opened = await asyncio.get_running_loop().run_in_executor(
                writer, _open_and_scan, path, key.public_key())
        except BaseException:
            writer.shutdown(wait=False)
            raise
        fd, scan = opened
        log = cls(fd, key, scan.head, path=path, ruri=ruri, clock=clock or SystemClock(),
                  group_commit=group_commit, size=scan.good_end, writer=writer)
        log._last_span = scan.last_span
        if scan.torn:
            await log.append(AuditRecord(
                event=AuditEvent.AUDIT_TAIL_RECOVERED,
                params={"cut_bytes": len(scan.torn),
                        "cut_sha256": hashlib.sha256(scan.torn).hexdigest(),
                        "after_seq": scan.head.last_seq},
            ))
        await log.checkpoint()
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

    async def append(self, record: AuditRecord, *, urgent: bool = False) -> AuditReceipt:
        """Chain, sign and durably write one entry; returns once it is fsynced.

        `urgent` (a stop): a group commit it is in does not wait a loop turn for more entries.
        """
        if not self.healthy:
            raise AuditWriteError(f"audit log {self.path} is not writable") from self._broken
        line, receipt = self._seal(record)
        if self._inline_ok():
            self._write_inline(line, receipt)
        else:
            loop = asyncio.get_running_loop()
            done: asyncio.Future[None] = loop.create_future()
            if self._loop_batch or self._loop_commit_ok():
                # A fast disk under load: the entries of this loop turn and the next share
                # one write+fsync, on the loop (no thread hand-off: cheaper than the thread's).
                if not self._loop_batch:
                    loop.call_soon(self._commit_next_turn)
                self._loop_batch.append((line, receipt, done))
                self._urgent = self._urgent or urgent
            else:
                self._queue.append((line, receipt, done))
                if self._flusher is None or self._flusher.done():
                    self._flusher = asyncio.create_task(self._flush())
            # A cancelled caller cancels only its wait: the entry is written anyway (its
            # future skipped), so no shield (a future more per entry).
            await done
        if (self._durable_seq - self._checkpointed_seq >= CHECKPOINT_EVERY
                and (self._checkpointing is None or self._checkpointing.done())):
            self._checkpointing = asyncio.create_task(self.checkpoint())  # off the reply path
        if self.listeners:  # after the caller's next step (its publish), not before it
            if not self._told:  # one loop callback for all the entries of a group commit
                asyncio.get_running_loop().call_soon(self._tell_listeners)
            self._told.append((record, receipt))
        return receipt

    def _tell_listeners(self) -> None:
        told, self._told = self._told, []
        for record, receipt in told:
            for listener in self.listeners:
                try:
                    listener(record, receipt)
                except Exception:
                    log.exception("audit listener failed")

    async def checkpoint(self) -> None:
        """Record the durable head as verified (every entry up to it is ours or was checked)."""
        if self._size == 0 or not self.healthy:
            return
        start, end = self._last_span
        cp = Checkpoint(seq=self._durable_seq, audit_id=self._durable_id, start=start, end=end)
        try:
            await asyncio.get_running_loop().run_in_executor(
                self._writer, _write_checkpoint, checkpoint_path(self.path), self._key, cp)
        except OSError:  # only start-up time suffers: the next start verifies more
            log.exception("audit checkpoint not written")
            return
        self._checkpointed_seq = cp.seq

    async def close(self) -> None:
        """Waits for queued writes, checkpoints, and releases the file and its lock.
        Idempotent."""
        if self._loop_batch:
            self._commit_loop_batch()
        pending = [t for t in (self._flusher, self._checkpointing) if t is not None]
        if pending:
            await asyncio.gather(*pending, return_exceptions=True)
        if self._fd >= 0:
            await self.checkpoint()
            os.close(self._fd)  # closing also drops the flock
            self._fd = -1
        self._writer.shutdown(wait=True)

    def _seal(self, record: AuditRecord) -> tuple[bytes, AuditReceipt]:
        """Assign seq and link synchronously, so the chain order is the call order."""
        ms = int(self._clock.time() * 1000)
        entry: dict[str, Any] = {
            k: v for k, v in msgspec.structs.asdict(record).items()
            if not (k in ("ai", "pending_id", "approvals") and v is None)
        }
        entry.update(
            seq=self._seq + 1, prev_hash=self._prev, timestamp=iso_utc(ms), timestamp_ms=ms,
            ruri=self._ruri, bridge="ros2", event=record.event.value,
        )
        audit_id = "sha256:" + hashlib.sha256(canonical(entry)).hexdigest()  # no id, no sig yet
        entry["audit_id"] = audit_id
        entry["sig"] = base64.b64encode(self._key.sign(audit_id.encode())).decode()
        self._seq += 1
        self._prev = audit_id
        return canonical(entry) + b"\n", AuditReceipt(seq=self._seq, audit_id=audit_id)

    async def _flush(self) -> None:
        loop = asyncio.get_running_loop()
        while self._queue:
            take = self._batch_limit or len(self._queue)
            batch, self._queue = self._queue[:take], self._queue[take:]
            data = b"".join(line for line, _, _ in batch)
            try:
                took = await loop.run_in_executor(self._writer, _write_durable, self._fd, data)
                self._durable(data, batch[-1][0], batch[-1][1], took)
            except Exception as exc:  # OSError, or a bug: no waiter may hang on it
                self._fail(batch + self._queue, exc)
                return
            _settle(batch)

    def _loop_commit_ok(self) -> bool:
        """Group commit on the loop: the disk is fast (smoothed write+fsync under
        INLINE_FSYNC_S) and no thread write is under way (entries stay in order)."""
        return (self._batch_limit == 0 and self._fsync_s < INLINE_FSYNC_S and not self._queue
                and (self._flusher is None or self._flusher.done()))

    def _commit_next_turn(self) -> None:
        """Runs the turn after the batch's first entry; commits in the turn after that, so
        what that turn seals joins the batch; at once if a stop is waiting."""
        if self._urgent or not self._loop_batch:
            self._commit_loop_batch()
        else:
            asyncio.get_running_loop().call_soon(self._commit_loop_batch)

    def _commit_loop_batch(self) -> None:
        batch, self._loop_batch = self._loop_batch, []
        self._urgent = False
        if not batch:  # committed already (by close)
            return
        if not self.healthy:
            self._fail(batch, OSError("the audit log is closed or broken"))
            return
        data = b"".join(line for line, _, _ in batch)
        try:
            took = _write_durable(self._fd, data)
        except Exception as exc:  # OSError, or a bug: no waiter may hang on it
            self._fail(batch, exc)
            return
        self._durable(data, batch[-1][0], batch[-1][1], took)
        _settle(batch)

    def _inline_ok(self) -> bool:
        if self._queue or self._loop_batch or (self._flusher is not None
                                                and not self._flusher.done()):
            return False
        quiet = time.monotonic() - self._last_write_end > INLINE_GAP_S
        return quiet and self._fsync_s < INLINE_FSYNC_S

    def _write_inline(self, line: bytes, receipt: AuditReceipt) -> None:
        try:
            took = _write_durable(self._fd, line)
        except Exception as exc:  # OSError, or a bug: either way the tail is unknown now
            self._fail([], exc)
            raise AuditWriteError(f"audit write to {self.path} failed: {exc}") from exc
        self._durable(line, line, receipt, took)

    def _durable(self, written: bytes, last: bytes, head: AuditReceipt, took_s: float) -> None:
        """Track the durable head (`last`, the line of `head`): seq, id and byte span."""
        self._fsync_s = 0.8 * self._fsync_s + 0.2 * took_s
        self._last_write_end = time.monotonic()
        self._size += len(written)
        self._last_span = (self._size - len(last), self._size)
        self._durable_seq, self._durable_id = head.seq, head.audit_id

    def _fail(self, waiting: list[_Queued], exc: Exception) -> None:
        # After a failed write the file's tail is unknown: refuse every further append.
        self._broken = exc
        self._queue = []
        for _, _, done in waiting:
            if not done.done():
                done.set_exception(AuditWriteError(f"audit write to {self.path} failed: {exc}"))


def _settle(batch: list[_Queued]) -> None:
    """Wakes the callers of a durable batch (a cancelled caller left; its entry is written)."""
    for _, _, done in batch:
        if not done.done():
            done.set_result(None)


def _make_dirs(*paths: Path) -> None:
    """Create each missing parent directory, private (0700): audit trails are not for all."""
    for path in paths:
        missing = [d for d in (path.parent, *path.parent.parents) if not d.exists()]
        for directory in reversed(missing):
            directory.mkdir(mode=0o700, exist_ok=True)
            os.chmod(directory, 0o700)  # mkdir's mode is filtered by the umask


def _open_and_scan(path: Path, pubkey: Ed25519PublicKey) -> tuple[int, _Scan]:
    created = not path.exists()
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        _lock(fd, path)
        scan = _scan_from_checkpoint(fd, path, pubkey)
        if scan.torn:
            os.ftruncate(fd, scan.good_end)
            full_fsync(fd)
        if created:
            fsync_dir(path.parent)
    except BaseException:
        os.close(fd)
        raise
    return fd, scan


def _scan_from_checkpoint(fd: int, path: Path, pubkey: Ed25519PublicKey) -> _Scan:
    cp = _read_checkpoint(checkpoint_path(path), pubkey)
    resume = _resume_point(fd, cp) if cp is not None else None
    seq, prev, offset = resume or (0, GENESIS, 0)
    if cp is not None and resume is None:
        log.warning("audit checkpoint does not match %s: verifying the whole log", path)
    data = _read_from(fd, offset)
    try:
        scan = _scan(data, pubkey, seq=seq, prev=prev)
    except AuditIntegrityError as exc:
        raise AuditIntegrityError(exc.seq, exc.detail + "; refusing to start",
                                  path=str(path)) from exc
    end = offset + scan.good_end
    span = (offset + scan.last_start, end) if scan.good_end else (
        (cp.start, cp.end) if resume and cp else (0, 0))
    return _Scan(head=scan.head, good_end=end, torn=scan.torn, last_span=span)


def _lock(fd: int, path: Path) -> None:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError as exc:
        raise AuditError(f"audit log {path} is in use by another process") from exc


def _read_from(fd: int, offset: int) -> bytes:
    os.lseek(fd, offset, os.SEEK_SET)
    chunks = []
    while chunk := os.read(fd, 1 << 20):
        chunks.append(chunk)
    return b"".join(chunks)
