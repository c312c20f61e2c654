"""§6 audit chain: JSON lines, SHA-256 links, Ed25519 signatures, durable group commit.

Each line is the canonical JSON of one entry. `audit_id` is "sha256:" + hex SHA-256 of the
canonical entry without `audit_id` and `sig`; `prev_hash` is the previous `audit_id` (the first
links to GENESIS); `sig` is base64 Ed25519 over `audit_id`.

Canonical JSON comes in two versions, told apart by the entry's `canonical` field (inside what
`audit_id` covers, so no entry can be moved from one to the other): entries that say
`"canonical": "rcan-canonical-json-v1"` (all written now) are RCAN canonical JSON v1, byte for
byte what the rcan SDK's `rcan.encoding.canonical_json` makes (sorted keys, no whitespace, raw
UTF-8, whole-number floats written as integers, other floats as Python's `repr`); entries
without it (written before) are sorted-keys msgspec JSON, where a whole float stays `50.0`.
Both verify; a log may hold both, older entries first. What a request puts in one entry (its
params as requested, ...) is held to the log's `request_bytes`, past which a marker stands for
it (`entry_bound`): canonical JSON writes `1e300` as 301 digits.

Writes run on the loop when the disk is fast (see INLINE_FSYNC_S), else on the log's own thread
(never the default executor, which costly reads may fill).
A signed checkpoint beside the log records the last verified entry (and the Merkle tree's peaks
there), so opening the log checks only what was appended after it: start-up time does not grow
with the log. Nor does its memory with what it checks (a crash may leave any number of
entries past the checkpoint, or a checkpoint that no longer matches): it reads and verifies one
line at a time (`log_tail.CHUNK` at once), and a torn tail is measured and hashed, never held.
`verify` and `rcan-rtps audit verify` still check the whole chain, a line at a time too.

Transparency (`treehead`, `merkle`): each commit batch, once durable, gets a signed tree head
(RFC 6962 root over the entries' lines) appended to `<log>.sth` and handed to the witness; the
tree is kept incrementally (O(log n) per entry). The public key is written beside the log
(`<log>.pub`), where `audit verify` finds it.

A failed write or fsync (a full disk) fails the callers of its batch and of every entry sealed
after it (they chain onto it; nothing was sent for them), cuts the file back to its last durable
length and rewinds the chain to the last durable entry: the next append works once the disk
does. Only when the file cannot be cut back does the log refuse further appends.
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
import json
import logging
import os
import stat
import time
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from ..events import Channel
from ._durable import (
    atomic_write,
    foreign_owner_problem,
    fsync_dir,
    full_fsync,
    not_regular_problem,
    read_small,
    read_small_with_stat,
    write_all,
)
from ._json import decode, decode_as
from .clock import Clock, SystemClock
from .entry_bound import (
    bound_request_content,
    canonical_float,
    request_bytes_limit,
    size_within,
)
from .errors import AuditError, AuditIntegrityError, AuditKeyError, AuditWriteError
from .keyfacts import read_public_pem
from .log_tail import CHUNK, lines_forwards
from .merkle import CompactTree, leaf_hash
from .treehead import TreeHead, TreeHeadFile, public_key_path, sign_tree_head, tree_head_path

if TYPE_CHECKING:
    from .witness import Witness

GENESIS = "sha256:" + "0" * 64
log = logging.getLogger(__name__)
_UNSIGNED = ("audit_id", "sig")
_REQUIRED = ("seq", "audit_id", "prev_hash", "sig", "event", "timestamp_ms")
CHECKPOINT_EVERY = 1000  # entries between checkpoints: bounds what a start after a crash re-checks
MAX_KEY_BYTES = 64 * 1024  # an Ed25519 key's PEM is 119 bytes; larger is no key
MAX_CHECKPOINT_BYTES = 64 * 1024  # a checkpoint holds at most 64 peaks: larger is not one
# What AuditLog.sign_resume_point signs before a start point's body. Its version changes with
# the meaning of the replay's state (governance.resume.StartPoint): an older point then fails
# its signature and is not used (the start replays from the boundary), never misread.
# A point's replay state must be what the replay from the boundary finds; a change of what an
# entry ends changes the tag, so that a point of the old meaning is not used (replayed from
# the boundary once). v2: a GOAL_FINISHED seeing no end ends nothing. v3: a move's entry ends
# the stream it says it replaced (`applied.replaces`).
RESUME_POINT_TAG = b"rcan-rtps resume point v3\n"
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
    ESTOP_REPEATED = "ESTOP_REPEATED"  # e-stops sent while already latched, counted together
    NETWORK_LOSS_SAFE_STOP = "NETWORK_LOSS_SAFE_STOP"
    GOAL_FINISHED = "GOAL_FINISHED"  # a goal the bridge sent ended; `outcome` says how
    STREAM_ENDED = "STREAM_ENDED"  # a velocity stream stopped sending (params.reason says why)
    INVOKE_RESULT = "INVOKE_RESULT"  # an RCAN INVOKE's result (§19.3), once decided
    # Another participant began / stopped publishing on a topic the bridge commands the robot
    # on (params: topic, type, participant, node, writers).
    FOREIGN_PUBLISHER = "FOREIGN_PUBLISHER"
    FOREIGN_PUBLISHER_GONE = "FOREIGN_PUBLISHER_GONE"
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
    # A stop executed although its body had these problems (see rcan._salvage).
    warnings: list[str] | None = None
    # A stop's signals went out before this entry was durable (they never wait for the disk).
    sent_first: bool | None = None
    # An RCAN 3.x message's envelope facts: version, ignored fields, firmware_hash,
    # attestation_ref, signature (see rcan._v3.Envelope.audit_facts).
    rcan: dict[str, Any] | None = None
    # An INVOKE_RESULT entry's: the INVOKE's msg_id and §19.5's status (the rcan-spec
    # conformance suite's names; `outcome` is the governor's decision on the skill's command).
    invoke_id: str | None = None
    status: str | None = None
    # The id a goal-starting command's goal is sent with, written ahead (a restart after a
    # crash cancels it by id: governance.resume).
    goal_id: str | None = None
    # An arm trajectory's entry: the boot clock when it was written (`{"boot_id": ...,
    # "ms": ...}`, `clock.BootInstant`), so that a restart in the same boot after a crash
    # knows how long it has run whatever the wall clock did (governance.resume).
    boot: dict[str, Any] | None = None


# The events whose `params` are a command's params as requested (its client's): held, with the
# rest of the request's content, to the log's request bound (`entry_bound`). Others' params are
# the bridge's own facts (a start's `left_running`, a goal's result), bounded where made and
# always logged whole.
_REQUESTED_PARAMS = frozenset({
    AuditEvent.COMMAND_DISPATCHED, AuditEvent.COMMAND_REJECTED, AuditEvent.COMMAND_FAILED,
    AuditEvent.PENDING_AUTH, AuditEvent.HITL_APPROVAL, AuditEvent.HITL_AUTHORIZED,
    AuditEvent.HITL_DENIED, AuditEvent.HITL_WITHDRAWN, AuditEvent.HITL_EXPIRED,
    AuditEvent.ESTOP, AuditEvent.ESTOP_CLEARED, AuditEvent.NETWORK_LOSS_SAFE_STOP,
})
# The request bound of a log opened without one: that of the default body limit (64 KiB).
DEFAULT_REQUEST_BYTES = request_bytes_limit(64 * 1024)

# Left out of an entry when None: older entries never had them.
_OPTIONAL = frozenset({"ai", "pending_id", "warnings", "sent_first", "approvals", "rcan",
                       "invoke_id", "status", "goal_id", "boot"})


class AuditReceipt(msgspec.Struct, frozen=True):
    seq: int
    audit_id: str


class ChainHead(msgspec.Struct, frozen=True):
    """Where a verified chain ends."""

    count: int
    last_seq: int
    last_audit_id: str


def canonical(obj: Any) -> bytes:
    """Sorted keys, no whitespace, UTF-8; floats in shortest round-trip form (entries from
    before RCAN canonical JSON v1, checkpoints and tree heads)."""
    return msgspec.json.encode(obj, order="sorted")


CANONICAL_V1 = "rcan-canonical-json-v1"
CANONICAL_KEY = "canonical"  # an entry's marker: which canonical JSON it is written in


def canonical_v1(obj: Any) -> bytes:
    """RCAN canonical JSON v1 (rcan-spec fixtures/canonical-json-v1.json): sorted keys, no
    whitespace, raw UTF-8, whole-number floats as integers (50.0 → 50, -0.0 → 0), other
    floats as Python's `json` writes them (the SDK's `canonical_json`, byte for byte)."""
    exponents: list[bool] = []
    return _encode_v1(_whole_floats_as_ints(obj, exponents), bool(exponents))


def _encode_v1(normal: Any, exponents: bool) -> bytes:
    """Already normalized: msgspec's bytes are `json`'s (keys, strings, ints alike) unless a
    float is written with an exponent (msgspec: 2.5e-05 as 0.000025, 1e-07 as 1e-7)."""
    if exponents:
        return json.dumps(normal, sort_keys=True, separators=(",", ":"),
                          ensure_ascii=False).encode("utf-8")
    return msgspec.json.encode(normal, order="sorted")


def _whole_floats_as_ints(value: Any, exponents: list[bool]) -> Any:
    """`value` with each whole float an int; notes in `exponents` a float written with one.
    A struct (an arm trajectory's points in `applied`) or a tuple is read as the JSON it is
    written as: left as it was, its whole floats were written `1.0` (an id the SDK, and
    `verify`, compute otherwise) and a float with an exponent beside it failed the append.
    A non-finite float (a stop's unknown param `1e400`, read as infinity) is null, as msgspec
    writes it: Python's json would write `Infinity`, which is not JSON (red team 28)."""
    if isinstance(value, msgspec.Struct):
        value = msgspec.to_builtins(value)
    if isinstance(value, float):
        written = canonical_float(value)
        if isinstance(written, float) and "e" in repr(written):
            exponents.append(True)
        return written
    if isinstance(value, dict):
        return {k: _whole_floats_as_ints(v, exponents) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_whole_floats_as_ints(v, exponents) for v in value]
    return value


def canonical_entry(entry: dict[str, Any]) -> bytes:
    """An entry in the canonical JSON its marker names."""
    if entry.get(CANONICAL_KEY) == CANONICAL_V1:
        return canonical_v1(entry)
    return canonical(entry)


def entry_id(entry: dict[str, Any]) -> str:
    body = {k: v for k, v in entry.items() if k not in _UNSIGNED}
    return "sha256:" + hashlib.sha256(canonical_entry(body)).hexdigest()


def carries_its_id(entry: dict[str, Any], audit_id: object) -> bool:
    """Whether `audit_id` is `entry`'s own id. False for an entry nested too deeply to hash
    (its canonical JSON is written recursively): no entry this log wrote is."""
    try:
        return entry_id(entry) == audit_id
    except RecursionError:
        return False


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


def check_log_file(path: str | os.PathLike[str]) -> None:
    """Raises AuditError if something is at `path` that is no regular file (a device such as
    /dev/null, which keeps no entry; a FIFO; a directory): what `run` and `config
    check` refuse before the start, which would only fail after joining the domain."""
    problem = not_regular_problem(path)
    if problem is not None:
        raise AuditError(f"audit log {problem}")


# The most config check reads back of a log (see check_log_contents): a busy robot's entries
# between two checkpoints are far fewer; a log of no checkpoint that grew past it is not read.
READ_BACK_LIMIT = 256 << 20


def check_log_contents(path: str | os.PathLike[str], key_path: str | os.PathLike[str], *,
                       limit: int = READ_BACK_LIMIT) -> str | None:
    """Raises the AuditError a start would raise reading the log at `path` back: a break in
    its chain since the checkpoint, a bad signature, entries another key signed (a replaced
    `key_path`), or entries with no key to verify them (the start would make a new one).
    Read only: no lock taken (a running bridge holds it), nothing cut or written — a torn
    tail, which the start cuts and audits, passes. No log, or an empty one, is fine.

    More than `limit` bytes to read (past the checkpoint, or the whole log where there is
    none that matches) are not read back: the log is read a line at a time (as the start
    reads it), but verifying takes time (some 0.2 ms an entry: a runaway log of gigabytes,
    many minutes). Returns what was not read, then, for a note."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise AuditError(f"cannot read audit log {path}: {exc}") from exc
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise AuditError(f"audit log {path} is not a regular file")
        if not os.path.lexists(key_path):
            if os.fstat(fd).st_size:
                raise AuditKeyError(
                    f"audit key {key_path} is missing, but the log {path} has entries: a "
                    "start would make a new key and refuse them (put the log's key back, or "
                    "start a new log)")
            return None
        _scan_from_checkpoint(fd, path, load_private_key(key_path).public_key(), limit=limit)
    except _TooLargeToRead as exc:
        return (f"audit log {path} not read back: {exc.size} bytes to verify, more than "
                f"config check reads ({limit}); a start reads them all")
    finally:
        os.close(fd)
    return None


def check_key_file(path: str | os.PathLike[str]) -> None:
    """Raises AuditKeyError if a key file is at `path` (a dangling link too) that a start
    would refuse; none there is fine (the start makes one). What `run` checks before it joins
    the domain, and `config check` with it: the two must agree."""
    if os.path.lexists(path):
        load_private_key(path)


def load_private_key(path: str | os.PathLike[str]) -> Ed25519PrivateKey:
    path = Path(path)
    try:
        # read_small: a FIFO at key_path held `run` (and `config check`) for a writer that
        # never came; a device or a huge file is no key either.
        pem, info = read_small_with_stat(path, MAX_KEY_BYTES)
    except (OSError, ValueError) as exc:
        raise AuditKeyError(f"cannot read audit key {path}: {exc}") from exc
    mode = info.st_mode
    owner = foreign_owner_problem(path, info)
    if owner is not None:
        raise AuditKeyError(f"audit key {owner}")
    # A signing key others can read lets them forge entries (and one they can write, swap it):
    # refuse, as ssh does.
    if mode & 0o077:
        raise AuditKeyError(f"audit key {path} is open to others (mode {mode & 0o777:o}): "
                            "it must be 0600")
    try:
        key = _ed25519_pkcs8(pem) or _load_pem(pem)
    except (ValueError, TypeError) as exc:
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


# The SubjectPublicKeyInfo DER of an Ed25519 key (RFC 8410) is this prefix and the 32-byte key.
_SPKI_ED25519 = bytes.fromhex("302a300506032b6570032100")


def public_key_pem(key: Ed25519PrivateKey) -> bytes:
    """The SubjectPublicKeyInfo PEM of `key`'s public key, the bytes `cryptography`'s PEM writer
    makes; made here for the same reason as `_ed25519_pkcs8_pem` (a run writes it at open)."""
    return public_key_pem_of(key.public_key())


def public_key_pem_of(key: Ed25519PublicKey) -> bytes:
    der = base64.b64encode(_SPKI_ED25519 + key.public_bytes_raw())  # one line
    return b"\n".join((b"-----BEGIN PUBLIC KEY-----", der, b"-----END PUBLIC KEY-----", b""))


def load_public_key(path: str | os.PathLike[str]) -> Ed25519PublicKey:
    try:
        return read_public_pem(path)
    except ValueError as exc:
        raise AuditKeyError(str(exc)) from exc


# -- verification ---------------------------------------------------------------------------


class _Scan(msgspec.Struct):
    head: ChainHead
    good_end: int  # byte offset just past the last complete, valid line
    torn: int  # bytes of an unterminated tail (a crash mid-append) after good_end, or 0
    last_start: int = 0  # byte offset of the last valid line
    last_span: tuple[int, int] = (0, 0)  # (start, end) of the last valid line in the file
    tree: CompactTree | None = None  # the Merkle tree of the valid lines, when asked for
    torn_sha256: str = ""  # of the torn tail, once the log is opened (what its entry records)


# (offset, line without its newline), in order. A scan of the file reads `log_tail.CHUNK` at a
# time (`lines_forwards`): it holds that and the longest line, never the part of the log it
# verifies (a crashed run's 200 000 entries past its checkpoint, 139 MB, were read whole and
# joined: 278 MB at once).
_Lines = Iterator[tuple[int, bytes]]


def _lines(data: bytes) -> _Lines:
    start = 0
    while start < len(data):
        end = data.find(b"\n", start)
        if end < 0:
            return
        yield start, data[start:end]
        start = end + 1


def _sha256_of(fd: int, start: int, end: int) -> str:
    """The hex SHA-256 of the file's bytes from `start` to `end`, a chunk at a time."""
    digest = hashlib.sha256()
    while start < end:
        block = os.pread(fd, min(CHUNK, end - start), start)
        if not block:
            break
        digest.update(block)
        start += len(block)
    return digest.hexdigest()


def _check_line(line: bytes, seq: int, prev: str, pubkey: Ed25519PublicKey | None) -> str:
    """Verify one line as entry `seq` after `prev`; returns its audit_id or raises."""
    try:
        entry = decode(line)
    except (msgspec.DecodeError, UnicodeDecodeError) as exc:
        raise AuditIntegrityError(seq, f"not JSON ({exc})") from exc
    if not isinstance(entry, dict) or not all(k in entry for k in _REQUIRED):
        raise AuditIntegrityError(seq, "not an audit entry")
    try:
        canonical_line, audit_id = canonical_entry(entry), entry_id(entry)
    except RecursionError as exc:  # (recursive: msgspec decodes deeper than this goes)
        raise AuditIntegrityError(seq, "nested too deeply to be an audit entry") from exc
    if canonical_line != line:
        raise AuditIntegrityError(seq, "not in canonical form")
    if entry["seq"] != seq:
        raise AuditIntegrityError(seq, f"found seq {entry['seq']!r} where {seq} belongs")
    if entry["prev_hash"] != prev:
        raise AuditIntegrityError(seq, "prev_hash does not link to the previous entry")
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


def _scan(lines: _Lines, pubkey: Ed25519PublicKey | None, *, seq: int = 0,
          prev: str = GENESIS, tree: CompactTree | None = None, start: int = 0,
          each: Callable[[int, str], None] | None = None) -> _Scan:
    """Verify `lines`, which begin at offset `start`, as the entries after `seq` (whose id is
    `prev`); each valid line is added to `tree` (the tree of the entries up to `seq`), if
    given, and then handed to `each` as (seq, audit_id). One line at a time: what is held
    does not grow with the lines. `torn` is left to the caller, which knows where its bytes
    end (past `good_end`: an unterminated tail)."""
    good_end = last_start = start
    for offset, line in lines:
        prev = _check_at(lines, line, seq + 1, prev, pubkey)
        seq += 1
        good_end, last_start = offset + len(line) + 1, offset
        if tree is not None:
            tree.append(leaf_hash(line))
        if each is not None:
            each(seq, prev)
    head = ChainHead(count=seq, last_seq=seq, last_audit_id=prev)
    return _Scan(head=head, good_end=good_end, torn=0, last_start=last_start, tree=tree)


def _check_at(rest: _Lines, line: bytes, seq: int, prev: str,
              pubkey: Ed25519PublicKey | None) -> str:
    """`_check_line`; a failure that nothing well-formed follows (in `rest`, the lines after
    `line`) is reported as the damaged last line it is (a torn tail, or an edit there)."""
    try:
        return _check_line(line, seq, prev, pubkey)
    except AuditIntegrityError as exc:
        if _only_damage_left(rest):
            raise AuditIntegrityError(exc.seq, "the last line is damaged (a torn tail, or "
                                      f"an edit): {exc.detail}") from exc
        raise


def _only_damage_left(rest: _Lines) -> bool:
    """No well-formed entry (one whose audit_id matches its content) is in `rest`: a failure
    before it is confined to the end of the file, as a crash mid-append leaves it."""
    return not any(_well_formed(line) for _, line in rest)


def _well_formed(line: bytes) -> bool:
    try:
        entry = decode(line)
    except (msgspec.DecodeError, UnicodeDecodeError):
        return False
    if not isinstance(entry, dict) or not all(k in entry for k in _REQUIRED):
        return False
    return carries_its_id(entry, entry.get("audit_id"))


def verify(
    path: str | os.PathLike[str], pubkey: Ed25519PublicKey | None = None
) -> ChainHead:
    """Verify a whole audit file; raises AuditIntegrityError naming the first bad seq.

    Without `pubkey` only the hash chain is checked (anyone could have rebuilt it). The file
    is read a line at a time (`verify_fd`), never held.
    """
    try:
        with open(path, "rb") as file:
            return verify_fd(file.fileno(), os.fstat(file.fileno()).st_size, pubkey)
    except AuditIntegrityError as exc:
        raise AuditIntegrityError(exc.seq, exc.detail, path=str(path)) from exc


def verify_fd(fd: int, end: int, pubkey: Ed25519PublicKey | None = None, *,
                tree: CompactTree | None = None, each: Callable[[int, str], None] | None = None,
                live: bool = False) -> ChainHead:
    """The entries of the open file `fd` up to byte `end`, verified from seq 1 as `verify_bytes`
    verifies them, a line at a time (`log_tail.CHUNK` and the longest line held, never the file: a
    month-long log of 700 MB took 1.4 GB to verify whole). Each valid entry is added to `tree`
    and handed to `each` (`_scan`); raises AuditIntegrityError at the first break, after the
    valid entries before it were. An unterminated tail is a torn last line, also an error —
    unless `live`: the log of a running bridge, whose last line may be being appended."""
    scan = _scan(lines_forwards(fd, 0, end), pubkey, tree=tree, each=each)
    if scan.good_end < end and not live:
        raise AuditIntegrityError(scan.head.last_seq + 1, "incomplete last line (torn tail)")
    return scan.head


def verify_bytes(data: bytes, pubkey: Ed25519PublicKey | None = None) -> ChainHead:
    """`verify` on the content of an audit file."""
    scan = _scan(_lines(data), pubkey)
    if scan.good_end < len(data):
        raise AuditIntegrityError(scan.head.last_seq + 1, "incomplete last line (torn tail)")
    return scan.head


# -- checkpoints ----------------------------------------------------------------------------


class Checkpoint(msgspec.Struct, frozen=True, kw_only=True):
    """The last verified entry: its seq, id and byte span, and the peaks of the Merkle tree of
    the entries up to it (hex; absent in checkpoints of older versions), signed with the log's
    key. A start-up aid, not a tree head: `<log>.sth` holds those."""

    seq: int
    audit_id: str
    start: int  # byte offset of the entry's line
    end: int  # just past its newline: where verification resumes
    tree: list[str] | None = None
    sig: str = ""

    def signed_bytes(self) -> bytes:
        body: dict[str, Any] = {"seq": self.seq, "audit_id": self.audit_id,
                                "start": self.start, "end": self.end}
        if self.tree is not None:
            body["tree"] = self.tree
        return canonical(body)

    def compact_tree(self) -> CompactTree | None:
        if self.tree is None:
            return None
        try:
            return CompactTree(self.seq, [bytes.fromhex(p) for p in self.tree])
        except ValueError:
            return None


def checkpoint_path(log_path: Path) -> Path:
    return log_path.with_name(log_path.name + ".checkpoint")


def _write_checkpoint(path: Path, key: Ed25519PrivateKey, cp: Checkpoint,
                      heads: TreeHeadFile | None = None) -> None:
    if heads is not None:
        heads.sync()  # the tree heads up to the checkpoint survive a power loss too
    sig = base64.b64encode(key.sign(cp.signed_bytes())).decode()
    atomic_write(path, msgspec.json.encode(msgspec.structs.replace(cp, sig=sig)))


def read_checkpoint(path: Path, pubkey: Ed25519PublicKey | None) -> Checkpoint:
    """The checkpoint at `path`, its signature checked when `pubkey` is given; raises OSError
    (FileNotFoundError if there is none) or ValueError (malformed, or not signed by `pubkey`)."""
    try:
        cp = decode_as(read_small(path, MAX_CHECKPOINT_BYTES), Checkpoint)
    except msgspec.DecodeError as exc:
        raise ValueError(f"checkpoint {path} is malformed: {exc}") from exc
    if pubkey is not None:
        try:
            pubkey.verify(base64.b64decode(cp.sig, validate=True), cp.signed_bytes())
        except (ValueError, InvalidSignature) as exc:
            raise ValueError(f"checkpoint {path} is not signed by this key") from exc
    return cp


def _read_checkpoint(path: Path, pubkey: Ed25519PublicKey) -> Checkpoint | None:
    """A checkpoint this key signed, or None (missing, unreadable, or not ours)."""
    try:
        return read_checkpoint(path, pubkey)
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        log.warning("audit checkpoint %s unusable: verifying the whole log", path)
        return None


def _resume_point(fd: int, cp: Checkpoint) -> tuple[int, str, int] | None:
    """(seq, audit_id, offset) to verify from, if the checkpointed line is still there."""
    size = os.fstat(fd).st_size
    if not 0 <= cp.start < cp.end <= size:
        return None
    line = os.pread(fd, cp.end - cp.start, cp.start)
    if not line.endswith(b"\n"):
        return None
    try:
        entry = decode(line[:-1])
    except msgspec.DecodeError:
        return None
    if not isinstance(entry, dict) or entry.get("seq") != cp.seq:
        return None
    if entry.get("audit_id") != cp.audit_id or not carries_its_id(entry, cp.audit_id):
        return None
    return cp.seq, cp.audit_id, cp.end


# -- the log --------------------------------------------------------------------------------


def _write_durable(fd: int, data: bytes) -> float:
    """Write and fsync; returns how long that took (seconds)."""
    started = time.perf_counter()
    write_all(fd, data)
    full_fsync(fd)
    return time.perf_counter() - started


class _TailUnknown(AuditWriteError):
    """A failed write could not be cut back: what the file ends with is unknown."""


_Signer = Callable[[CompactTree], TreeHead]


def _commit(fd: int, lines: list[bytes], size_before: int, tree: CompactTree | None,
            sign: _Signer, heads: TreeHeadFile | None
            ) -> tuple[float, CompactTree | None, TreeHead | None]:
    """Write and fsync a batch, then its tree head. A failed write is cut back to
    `size_before` (the durable length) and re-raised; `_TailUnknown` if it cannot be.
    Returns the write+fsync time, the grown tree and the batch's tree head."""
    try:
        took = _write_durable(fd, b"".join(lines))
    except Exception as exc:
        _cut_back(fd, size_before, exc)
        raise
    if tree is None:  # lost by an earlier failure (logged): no more heads until a restart
        return took, None, None
    try:  # the entries are durable: nothing here may turn that into a failure
        grown = tree.copy()
        grown.extend(leaf_hash(line[:-1]) for line in lines)
        head = sign(grown)
        if heads is not None:
            heads.append(head)
    except Exception:
        log.exception("audit tree head not made: no more tree heads until a restart")
        return took, None, None
    return took, grown, head


def _cut_back(fd: int, size: int, cause: Exception) -> None:
    try:
        os.ftruncate(fd, size)
        full_fsync(fd)
    except OSError as exc:
        raise _TailUnknown(f"{cause}; then cutting back failed: {exc}") from exc


_Queued = tuple[bytes, AuditReceipt, "asyncio.Future[None]"]  # a sealed line awaiting its fsync


class AuditLog:
    """The append-only chain. `append` returns only once its entry is on disk (fsynced).

    With `group_commit`, appends of two loop turns, or that arrive while the writer thread's
    write+fsync is running, share the next one. Each commit's tree head follows its fsync.
    """

    def __init__(self, fd: int, key: Ed25519PrivateKey, head: ChainHead, *, path: Path,
                 ruri: str | None, clock: Clock, group_commit: bool, size: int,
                 writer: concurrent.futures.ThreadPoolExecutor,
                 tree: CompactTree | None = None, heads: TreeHeadFile | None = None,
                 witness: Witness | None = None,
                 audited: Channel[[AuditRecord, AuditReceipt]] | None = None,
                 request_bytes: int = DEFAULT_REQUEST_BYTES) -> None:
        self.path = path
        # What a request may put in one entry (`entry_bound`): `request_bytes_limit` of the
        # config's `api.max_body_bytes`.
        self.request_bytes = request_bytes
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
        self._tree = tree  # the Merkle tree of the durable entries (None: lost, no heads)
        self._heads = heads  # <log>.sth
        self._witness = witness
        self._checkpointed_seq = -1  # none written by this process yet
        self._fsync_s = 0.0  # smoothed write+fsync time
        self._checkpointing: asyncio.Task[None] | None = None
        self._checkpoint_hooks: list[Callable[[Checkpoint], None]] = []
        # Runs the hooks (a start point replays up to 1000 entries: 6–30 ms), one at a time,
        # in checkpoint order, beside the writer thread rather than on it: the entries written
        # meanwhile — commands waiting to reach the robot — do not wait for them.
        self._hook_thread: concurrent.futures.ThreadPoolExecutor | None = None
        self._last_write_end = 0.0
        # Told of every durable entry (e.g. metrics); a failing listener is logged, not raised.
        self.audited: Channel[[AuditRecord, AuditReceipt]] = audited or Channel("audit")
        self._told: list[tuple[AuditRecord, AuditReceipt]] = []  # durable, listeners not told

    @classmethod
    async def open(cls, path: str | os.PathLike[str], key_path: str | os.PathLike[str], *,
                   ruri: str | None = None, clock: Clock | None = None,
                   group_commit: bool = True, witness: str | None = None,
                   audited: Channel[[AuditRecord, AuditReceipt]] | None = None,
                   request_bytes: int = DEFAULT_REQUEST_BYTES) -> AuditLog:
        """Open (or create) the log, verify what the checkpoint does not cover, cut a torn tail.

        A torn tail is cut and audited. Any other break raises AuditIntegrityError: the bridge
        must not start on it. Missing directories are created (mode 0700). The public key is
        written beside the log (`<log>.pub`); tree heads go to `<log>.sth` and, with
        `witness` (a file://, http:// or https:// URL), to the witness too. `request_bytes`:
        the most a request's content takes in one entry (`entry_bound.request_bytes_limit`
        of the body limit); past it, a marker stands for it.
        """
        path = Path(path)
        writer = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="rcan-audit")
        try:
            sender = _witness(witness)
            loop = asyncio.get_running_loop()
            await loop.run_in_executor(writer, _make_dirs, path, Path(key_path))
            key = load_or_create_key(key_path)
            fd, scan = await loop.run_in_executor(writer, _open_and_scan, path,
                                                  key.public_key())
            heads = await loop.run_in_executor(writer, _open_sidecars, path, key)
        except BaseException:
            writer.shutdown(wait=False)
            raise
        log = cls(fd, key, scan.head, path=path, ruri=ruri, clock=clock or SystemClock(),
                  group_commit=group_commit, size=scan.good_end, writer=writer,
                  tree=scan.tree, heads=heads, witness=sender, audited=audited,
                  request_bytes=request_bytes)
        log._last_span = scan.last_span
        if scan.torn:
            await log.append(AuditRecord(
                event=AuditEvent.AUDIT_TAIL_RECOVERED,
                params={"cut_bytes": scan.torn, "cut_sha256": scan.torn_sha256,
                        "after_seq": scan.head.last_seq},
            ))
        else:  # a head for what is there (older logs have none; the witness learns of it)
            await log._publish_head()
        await log.checkpoint()
        return log

    @property
    def public_key(self) -> Ed25519PublicKey:
        return self._key.public_key()

    def sign_digest(self, digest: bytes) -> bytes:
        """Ed25519 by the log's key over a 32-byte digest (an audit export's chain root, §20).
        The log's other signatures are over text of 71 bytes or more (audit ids, tree heads,
        checkpoints), so none of them can stand for one of these, nor the other way round."""
        if len(digest) != 32:
            raise ValueError("a digest is 32 bytes")
        return self._key.sign(digest)

    def logs_whole(self, params: dict[str, Any]) -> bool:
        """Whether a command's `params` would be logged whole (within `request_bytes`): a
        command that is to run must be (`Governor` refuses it otherwise)."""
        return size_within(params, self.request_bytes) is not None

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
        return await self._enter(record, urgent=urgent, inline=True)

    def seal(self, record: AuditRecord, *, urgent: bool = False) -> Awaitable[AuditReceipt]:
        """Chain and sign one entry now, in this call, and queue it; the result, awaited,
        returns once it is fsynced. A stop's: its place in the chain is the moment it took
        effect (no entry sealed after this call precedes it), and nothing is written in this
        call (never inline), so what the caller does next (tell the robot) does not wait for
        the disk. Raises AuditWriteError at once if the log is unwritable; the result must be
        awaited (or its entry is written without anyone learning whether it was)."""
        return self._enter(record, urgent=urgent, inline=False)

    def _enter(self, record: AuditRecord, *, urgent: bool, inline: bool
               ) -> Coroutine[Any, Any, AuditReceipt]:
        """Seal `record` and write it inline or queue it for a commit, all before returning;
        the coroutine returned waits for its commit. `inline`: it may be written here."""
        if not self.healthy:
            raise AuditWriteError(f"audit log {self.path} is not writable") from self._broken
        line, receipt = self._seal(record)
        if inline and self._inline_ok():
            self._write_inline(line, receipt)
            return self._committed(record, receipt, None)
        loop = asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()
        if self._loop_batch or self._loop_commit_ok():
            # A fast disk under load: the entries of this loop turn and the next share
            # one write+fsync, on the loop (no thread hand-off: cheaper than the thread's).
            if not self._loop_batch:
                loop.call_soon(self._commit_next_turn)
            # Urgent: its batch commits the turn it is due, without a turn more for others.
            # A sealed entry (not inline) that joins a batch whose commit is queued already
            # leaves it as it was: commit now would run ahead of its caller's next step.
            self._urgent = self._urgent or (urgent and (inline or len(self._loop_batch) == 0))
            self._loop_batch.append((line, receipt, done))
        else:
            self._queue.append((line, receipt, done))
            if self._flusher is None or self._flusher.done():
                self._flusher = asyncio.create_task(self._flush())
        return self._committed(record, receipt, done)

    async def _committed(self, record: AuditRecord, receipt: AuditReceipt,
                         done: asyncio.Future[None] | None) -> AuditReceipt:
        """Waits for the commit of a sealed entry (`done`; None: written inline already)."""
        if done is not None:
            # A cancelled caller cancels only its wait: the entry is written anyway (its
            # future skipped), so no shield (a future more per entry).
            await done
        if (self._durable_seq - self._checkpointed_seq >= CHECKPOINT_EVERY
                and (self._checkpointing is None or self._checkpointing.done())):
            self._checkpointing = asyncio.create_task(self.checkpoint())  # off the reply path
        if self.audited.heard:  # after the caller's next step (its publish), not before it
            if not self._told:  # one loop callback for all the entries of a group commit
                asyncio.get_running_loop().call_soon(self._tell_listeners)
            self._told.append((record, receipt))
        return receipt

    def _tell_listeners(self) -> None:
        told, self._told = self._told, []
        for record, receipt in told:
            self.audited.emit(record, receipt)

    async def checkpoint(self) -> None:
        """Record the durable head as verified (every entry up to it is ours or was checked)."""
        if self._size == 0 or not self.healthy:
            return
        start, end = self._last_span
        tree = self._tree
        peaks = [p.hex() for p in tree.peaks] if tree is not None else None
        cp = Checkpoint(seq=self._durable_seq, audit_id=self._durable_id, start=start, end=end,
                        tree=peaks)
        try:
            await asyncio.get_running_loop().run_in_executor(
                self._writer, _write_checkpoint, checkpoint_path(self.path), self._key, cp,
                self._heads)
        except OSError:  # only start-up time suffers: the next start verifies more
            log.exception("audit checkpoint not written")
            return
        self._checkpointed_seq = cp.seq
        for hook in self._checkpoint_hooks:
            try:
                await asyncio.get_running_loop().run_in_executor(self._hook_thread, hook, cp)
            except Exception:  # a start-up aid: the next start replays more
                log.exception("audit checkpoint hook failed")

    def on_checkpoint(self, hook: Callable[[Checkpoint], None]) -> None:
        """Run `hook` after each checkpoint (every CHECKPOINT_EVERY entries and at close), with
        that checkpoint, on a thread of the hooks' own (one at a time, in order) while entries
        go on being written: the file holds every entry up to the checkpoint, and those bytes
        no longer change."""
        if self._hook_thread is None:
            self._hook_thread = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix="rcan-audit-hooks")
        self._checkpoint_hooks.append(hook)

    def sign_resume_point(self, body: bytes) -> bytes:
        """Ed25519 by the log's key over RESUME_POINT_TAG + `body` (governance.resume's start
        points). The tag starts no other message the key signs (audit ids, tree heads,
        checkpoints, 32-byte digests), so none can stand for one of these."""
        return self._key.sign(RESUME_POINT_TAG + body)

    async def close(self) -> None:
        """Waits for queued writes, checkpoints, sends the last tree heads to the witness
        (2 s at most) and releases the files and the lock. Idempotent."""
        if self._loop_batch:
            self._commit_loop_batch()
        pending = [t for t in (self._flusher, self._checkpointing) if t is not None]
        if pending:
            await asyncio.gather(*pending, return_exceptions=True)
        if self._fd >= 0:
            await self.checkpoint()
            os.close(self._fd)  # closing also drops the flock
            self._fd = -1
        loop = asyncio.get_running_loop()
        heads, self._heads = self._heads, None
        witness, self._witness = self._witness, None
        if heads is not None:
            await loop.run_in_executor(self._writer, heads.close)
        if witness is not None:
            await loop.run_in_executor(self._writer, witness.close)
        self._writer.shutdown(wait=True)
        if self._hook_thread is not None:  # (idle: the last checkpoint waited for its hooks)
            self._hook_thread.shutdown(wait=True)

    def _seal(self, record: AuditRecord) -> tuple[bytes, AuditReceipt]:
        """Assign seq and link synchronously, so the chain order is the call order."""
        ms = int(self._clock.time() * 1000)
        entry: dict[str, Any] = {
            k: v for k, v in msgspec.structs.asdict(record).items()
            if not (k in _OPTIONAL and v is None)
        }
        bound_request_content(entry, self.request_bytes,
                              params=record.event in _REQUESTED_PARAMS)
        entry.update(
            seq=self._seq + 1, prev_hash=self._prev, timestamp=iso_utc(ms), timestamp_ms=ms,
            ruri=self._ruri, bridge="ros2", event=record.event.value,
        )
        entry[CANONICAL_KEY] = CANONICAL_V1
        exponents: list[bool] = []
        normal = _whole_floats_as_ints(entry, exponents)  # once, for both encodings
        body = _encode_v1(normal, bool(exponents))  # no id, no sig yet
        audit_id = "sha256:" + hashlib.sha256(body).hexdigest()
        normal["audit_id"] = audit_id
        normal["sig"] = base64.b64encode(self._key.sign(audit_id.encode())).decode()
        self._seq += 1
        self._prev = audit_id
        line = _encode_v1(normal, bool(exponents))
        return line + b"\n", AuditReceipt(seq=self._seq, audit_id=audit_id)

    def _sign_head(self, tree: CompactTree) -> TreeHead:
        return sign_tree_head(self._key, tree.size, tree.root(), int(self._clock.time() * 1000))

    async def _publish_head(self) -> None:
        """A tree head for the durable entries, outside any commit (at open)."""
        tree = self._tree
        if tree is None or tree.size == 0:
            return
        head = self._sign_head(tree)
        if self._heads is not None:
            await asyncio.get_running_loop().run_in_executor(self._writer, self._heads.append,
                                                             head)
        if self._witness is not None:
            self._witness.submit(head.line())

    async def _flush(self) -> None:
        loop = asyncio.get_running_loop()
        while self._queue:
            take = self._batch_limit or len(self._queue)
            batch, self._queue = self._queue[:take], self._queue[take:]
            lines = [line for line, _, _ in batch]
            try:
                took, tree, head = await loop.run_in_executor(
                    self._writer, _commit, self._fd, lines, self._size, self._tree,
                    self._sign_head, self._heads)
            except Exception as exc:  # OSError, or a bug: no waiter may hang on it
                self._fail(batch, exc)
                return
            self._durable(lines, batch[-1][1], took, tree, head)
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
        lines = [line for line, _, _ in batch]
        try:
            took, tree, head = _commit(self._fd, lines, self._size, self._tree,
                                       self._sign_head, self._heads)
        except Exception as exc:  # OSError, or a bug: no waiter may hang on it
            self._fail(batch, exc)
            return
        self._durable(lines, batch[-1][1], took, tree, head)
        _settle(batch)

    def _inline_ok(self) -> bool:
        if self._queue or self._loop_batch or (self._flusher is not None
                                                and not self._flusher.done()):
            return False
        quiet = time.monotonic() - self._last_write_end > INLINE_GAP_S
        return quiet and self._fsync_s < INLINE_FSYNC_S

    def _write_inline(self, line: bytes, receipt: AuditReceipt) -> None:
        try:
            took, tree, head = _commit(self._fd, [line], self._size, self._tree,
                                       self._sign_head, self._heads)
        except Exception as exc:  # OSError, or a bug
            self._fail([], exc)
            raise AuditWriteError(f"audit write to {self.path} failed: {exc}") from exc
        self._durable([line], receipt, took, tree, head)

    def _durable(self, lines: list[bytes], last: AuditReceipt, took_s: float,
                 tree: CompactTree | None, head: TreeHead | None) -> None:
        """Track the durable end (`last`, the receipt of the last of `lines`): seq, id, byte
        span and tree; hand the batch's tree head to the witness."""
        self._fsync_s = 0.8 * self._fsync_s + 0.2 * took_s
        self._last_write_end = time.monotonic()
        self._size += sum(len(line) for line in lines)
        self._last_span = (self._size - len(lines[-1]), self._size)
        self._durable_seq, self._durable_id = last.seq, last.audit_id
        self._tree = tree
        if head is not None and self._witness is not None:
            self._witness.submit(head.line())

    def _fail(self, batch: list[_Queued], exc: Exception) -> None:
        """A commit failed: its entries and every one sealed after it (they chain onto it)
        are refused. The file was cut back to its durable length, so the chain goes on from
        the last durable entry; if it could not be (`_TailUnknown`), the log refuses more."""
        waiting = batch + self._queue + self._loop_batch
        self._queue, self._loop_batch, self._urgent = [], [], False
        if isinstance(exc, _TailUnknown) or self._fd < 0:
            self._broken = exc
            log.error("audit log %s unwritable until a restart: %s", self.path, exc)
        else:
            self._seq, self._prev = self._durable_seq, self._durable_id
            log.error("audit write to %s failed: %s; %d entries refused, the log goes on from "
                      "seq %d", self.path, exc, len(waiting) or 1, self._durable_seq)
        for _, _, done in waiting:
            if not done.done():
                error = AuditWriteError(f"audit write to {self.path} failed: {exc}")
                error.__cause__ = exc
                done.set_exception(error)


def _settle(batch: list[_Queued]) -> None:
    """Wakes the callers of a durable batch (a cancelled caller left; its entry is written)."""
    for _, _, done in batch:
        if not done.done():
            done.set_result(None)


def _witness(url: str | None) -> Witness | None:
    if url is None:
        return None
    from .witness import Witness  # its thread and imports only where one is configured

    return Witness(url)


def _held_there(path: Path, size: int) -> bytes | None:
    """The bytes of `path` if it is a regular file of at most `size` bytes, else None (then it
    is written afresh): a FIFO there would hold the start for a writer that never comes."""
    try:
        return read_small(path, size)
    except (FileNotFoundError, ValueError):
        return None


def _make_dirs(*paths: Path) -> None:
    """Create each missing parent directory, private (0700): audit trails are not for all."""
    for path in paths:
        missing = [d for d in (path.parent, *path.parent.parents) if not d.exists()]
        for directory in reversed(missing):
            directory.mkdir(mode=0o700, exist_ok=True)
            os.chmod(directory, 0o700)  # mkdir's mode is filtered by the umask


def _open_sidecars(path: Path, key: Ed25519PrivateKey) -> TreeHeadFile | None:
    """Write the public key beside the log (if it is not there already) and open the tree-head
    file. Neither is the record: a failure is logged, and the log works without them."""
    pub = public_key_path(path)
    pem = public_key_pem(key)
    try:
        if _held_there(pub, len(pem)) != pem:
            atomic_write(pub, pem, mode=0o644)
    except OSError as exc:
        log.warning("audit public key not written to %s: %s", pub, exc)
    try:
        return TreeHeadFile(tree_head_path(path))
    except OSError as exc:
        log.error("audit tree heads %s cannot be opened: %s (no tree heads will be written "
                  "there)", tree_head_path(path), exc)
        return None


def _open_and_scan(path: Path, pubkey: Ed25519PublicKey) -> tuple[int, _Scan]:
    created = not path.exists()
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # /dev/null keeps no entry
            raise AuditError(f"audit log {path} is not a regular file")
        _lock(fd, path)
        scan = _scan_from_checkpoint(fd, path, pubkey)
        if scan.torn:
            scan.torn_sha256 = _sha256_of(fd, scan.good_end, scan.good_end + scan.torn)
            os.ftruncate(fd, scan.good_end)
            full_fsync(fd)
        if created:
            fsync_dir(path.parent)
    except BaseException:
        os.close(fd)
        raise
    return fd, scan


def _scan_from_checkpoint(fd: int, path: Path, pubkey: Ed25519PublicKey, *,
                          limit: int | None = None) -> _Scan:
    """The log verified from its checkpoint, line by line (`limit`: raise _TooLargeToRead
    rather than read more bytes than that)."""
    cp = _read_checkpoint(checkpoint_path(path), pubkey)
    resume = _resume_point(fd, cp) if cp is not None else None
    if cp is not None and resume is None:
        log.warning("audit checkpoint does not match %s: verifying the whole log", path)
    size = os.fstat(fd).st_size  # (the end of what is verified: a line appended later is not)
    _within(limit, size - (0 if resume is None else resume[2]))
    tree = _resume_tree(fd, cp, resume, limit)
    if tree is None:
        resume, tree = None, CompactTree()
        _within(limit, size)
    seq, prev, offset = resume or (0, GENESIS, 0)
    try:
        scan = _scan(lines_forwards(fd, offset, size), pubkey, seq=seq, prev=prev, tree=tree,
                     start=offset)
    except AuditIntegrityError as exc:
        raise AuditIntegrityError(exc.seq, exc.detail + _replaced_key_hint(path, pubkey)
                                  + "; refusing to start", path=str(path)) from exc
    end = scan.good_end
    span = (scan.last_start, end) if end > offset else (
        (cp.start, cp.end) if resume and cp else (0, 0))
    return _Scan(head=scan.head, good_end=end, torn=size - end, last_span=span, tree=scan.tree)


def _replaced_key_hint(path: Path, pubkey: Ed25519PublicKey) -> str:
    """What a log that does not verify says when the key beside it (`<log>.pub`, written by
    the runs that signed it) is not the signing key's: a key_path replaced (or pointed at
    another key) is why, not a damaged log. Else nothing."""
    pub = _held_there(public_key_path(path), MAX_KEY_BYTES)
    if pub is None or pub == public_key_pem_of(pubkey):
        return ""
    return (f" (the signing key is not the one {public_key_path(path).name} holds: a replaced "
            "key_path? key rotation is not supported — put the log's key back, or start a "
            "new log)")


def _resume_tree(fd: int, cp: Checkpoint | None, resume: tuple[int, str, int] | None,
                 limit: int | None = None) -> CompactTree | None:
    """The Merkle tree at the checkpoint: its peaks, or (a checkpoint of an older version)
    the lines it vouches for, hashed once. None: verify and hash from the start instead."""
    if cp is None or resume is None:
        return CompactTree()
    tree = cp.compact_tree()
    if tree is not None:
        return tree
    _within(limit, os.fstat(fd).st_size)
    tree = CompactTree()
    tree.extend(leaf_hash(line) for _, line in lines_forwards(fd, 0, resume[2]))
    return tree if tree.size == cp.seq else None


def _lock(fd: int, path: Path) -> None:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError as exc:
        raise AuditError(f"audit log {path} is in use by another process") from exc


class _TooLargeToRead(AuditError):
    def __init__(self, size: int) -> None:
        super().__init__(size)
        self.size = size


def _within(limit: int | None, size: int) -> None:
    """Raises _TooLargeToRead if `size` bytes are more than `limit` to read."""
    if limit is not None and size > limit:
        raise _TooLargeToRead(size)
