"""Checking an audit log against what anchors it, and proofs over it (`rcan-rtps audit ...`).

`check_log` verifies the chain (links, hashes, canonical form, signatures when a key is given)
and then every anchor: the tree heads in `<log>.sth`, those of witness files, and the start-up
checkpoint. A head must be signed by the key and its root must be the root of the log's first
`tree_size` entries; a head (or checkpoint) naming more entries than the log holds means the
log was truncated, and is reported by name. Proofs are RFC 9162 inclusion and consistency
proofs, built from the log's lines (the leaf of entry `seq` is its line without the newline).

Nothing here holds the log or a file of tree heads: both grow for as long as the robot runs
(a month-long log of 700 MB took 1.4 GB to check whole, out of memory on a 4 GB robot
computer). The log is read once, a line at a time (`audit.verify_fd`), and each head is
checked against the log's root when the scan reaches its size (heads are written in the order
of their sizes); the few that are not in order wait for a second pass over the log's lines.
A proof is the roots of ranges of leaves computed in one pass (`merkle.roots_of_ranges`).

The problems listed are bounded too: the first `PROBLEMS_LISTED` of each file of tree heads
and of the heads that do not match the log, then one line counting the rest (a tree-head file
with millions of bad lines made a report of millions of lines, and the API's verify answer a
JSON list as long).
"""

from __future__ import annotations

import collections
import contextlib
import heapq
import itertools
import os
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from ._durable import regular_file
from .audit import checkpoint_path, read_checkpoint, verify_fd
from .errors import AuditError, AuditIntegrityError
from .log_tail import lines_forwards
from .merkle import (
    EMPTY_ROOT,
    CompactTree,
    consistency_ranges,
    inclusion_ranges,
    leaf_hash,
    roots_of_ranges,
    verify_consistency,
    verify_inclusion,
)
from .treehead import (
    BadTreeHead,
    HeadLines,
    TreeHead,
    signature_ok,
    tree_head_path,
)

PROBLEMS_LISTED = 100  # of each file of tree heads, and of the heads that do not match


class LogReport(msgspec.Struct, kw_only=True):
    entries: int = 0  # valid entries, in order from seq 1
    last_audit_id: str | None = None  # of the last valid entry
    bad_seq: int | None = None  # where the chain broke, if it did
    heads: int = 0  # tree heads checked (the sidecar's)
    witnessed: int = 0  # tree heads checked from witness files
    newest: TreeHead | None = None  # the largest head that matched
    problems: list[str] = msgspec.field(default_factory=list)
    notes: list[str] = msgspec.field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


class _Anchor(msgspec.Struct, frozen=True):
    source: str
    head: TreeHead
    order: tuple[int, int]  # (its file's place, its line): the order it is reported in
    witnessed: bool  # from a witness file, not the log's own tree heads


class _HeadFile:
    """One file of tree heads (the log's sidecar or a witness's), read a line at a time as
    the log is scanned: its valid heads in file order (`next`), what is wrong with the
    others (`problems`), a note of its torn tail."""

    def __init__(self, place: int, source: str, *problems: str) -> None:
        self.place, self.source = place, source
        self.problems = list(problems)
        self.unlisted = 0  # problems beyond the first PROBLEMS_LISTED, counted only
        self.notes: list[str] = []
        self.valid = 0  # valid heads read so far
        self.next: _Anchor | None = None
        self._heads: Iterator[_Anchor] = iter(())

    def open(self, file: Path, pubkey: Ed25519PublicKey | None,
             files: contextlib.ExitStack) -> None:
        """Its size is taken now: in a live log's check, before the log's own (a head is
        written only once its entries are durable, so every head read names entries on disk)."""
        try:  # (ValueError: a FIFO, say, which would never end)
            fd, info = files.enter_context(regular_file(file))
        except FileNotFoundError:
            return
        except (OSError, ValueError) as exc:
            self._problem(f"{self.source}: cannot read {file}: {exc}")
            return
        self._heads = self._read(HeadLines(fd, info.st_size), file, pubkey)

    def _read(self, lines: HeadLines, file: Path,
              pubkey: Ed25519PublicKey | None) -> Iterator[_Anchor]:
        try:
            for n, head in lines:
                if isinstance(head, BadTreeHead):
                    self._problem(f"{self.source} line {head.line_no}: {head.problem}")
                elif pubkey is not None and not signature_ok(head, pubkey):
                    self._problem(f"{self.source} line {n}: {head.describe()} has a bad "
                                  "signature")
                else:
                    self.valid += 1
                    yield _Anchor(f"{self.source} line {n}", head, (self.place, n),
                                  witnessed=self.place > 0)
        except OSError as exc:  # (an I/O error part way)
            self._problem(f"{self.source}: cannot read {file}: {exc}")
        if lines.torn:
            self.notes.append(f"{self.source}: an incomplete last line ignored ({lines.torn} "
                              "bytes; a crash while it was written)")

    def advance(self) -> None:
        self.next = next(self._heads, None)

    def _problem(self, text: str) -> None:
        if len(self.problems) < PROBLEMS_LISTED:
            self.problems.append(text)
        else:
            self.unlisted += 1


def check_log(path: Path, pubkey: Ed25519PublicKey | None,
              witness_files: Sequence[Path] = (), *, live: bool = False) -> LogReport:
    """Everything `audit verify` checks. Raises OSError only when the log cannot be read and
    nothing anchors it (then there is nothing to check).

    `live`: the log of a running bridge. Its tree heads' sizes are taken before its own (see
    `_HeadFile.open`), and a last line still being appended is not an entry yet."""
    report = LogReport()
    with contextlib.ExitStack() as files:
        heads = [_HeadFile(0, "tree heads")]
        heads[0].open(tree_head_path(path), pubkey, files)
        for witness in witness_files:
            if not witness.exists():
                heads.append(_HeadFile(len(heads), "", f"witness file {witness} does not "
                                       "exist"))
                continue
            heads.append(_HeadFile(len(heads), f"witness {witness}"))
            heads[-1].open(witness, pubkey, files)
        checkpoint, checkpoint_problems = _checkpoint(path, pubkey)
        try:
            log_fd: int | None = files.enter_context(open(path, "rb")).fileno()
        except FileNotFoundError as exc:
            log_fd, missing = None, exc
        end = 0 if log_fd is None else _size(log_fd)
        roots = _RootCheck(heads, checkpoint[0] if checkpoint else None, report)
        chain = _verify_chain(log_fd, end, pubkey, roots, live, report)
        roots.finish(lambda sizes: _roots_at(log_fd, end, sizes))
    anchored = any(file.valid for file in heads)
    if log_fd is None:
        if not anchored and checkpoint is None:
            raise missing
        checkpoint_problems.append(f"{path} is missing, but tree heads or a checkpoint name "
                                   "its entries")
    report.problems = [*(p for file in heads for p in file.problems), *checkpoint_problems,
                       *chain, *roots.problems()]
    if checkpoint is not None:
        _checkpoint_holds(checkpoint, roots.checkpoint_id, report)
    unlisted = sum(file.unlisted for file in heads) + roots.unlisted
    if unlisted:
        report.problems.append(f"{unlisted} more problems with tree heads not listed (the "
                               f"first {PROBLEMS_LISTED} of each file, and of the heads that "
                               "do not match the log, are)")
    report.notes = [n for file in heads for n in file.notes]
    _notes(report, pubkey, anchored, checkpoint)
    return report


def _size(fd: int) -> int:
    return os.fstat(fd).st_size


def _verify_chain(fd: int | None, end: int, pubkey: Ed25519PublicKey | None,
                  roots: _RootCheck, live: bool, report: LogReport) -> list[str]:
    """The chain verified a line at a time, each entry handed to `roots`; what broke it."""
    tree = roots.tree
    try:
        if fd is not None:
            verify_fd(fd, end, pubkey, tree=tree, each=roots.entry, live=live)
    except AuditIntegrityError as exc:
        report.bad_seq = exc.seq
        return [str(exc)]
    finally:
        report.entries = tree.size
    return []


class _RootCheck:
    """Each anchor's head checked against the root of the log's first `tree_size` entries
    when the scan has verified that many (`entry`, for each valid entry in order); the id of
    the checkpoint's entry. A head smaller than one before it in its file (the log writes
    them in order) is checked after the scan, from a second pass over the log's lines."""

    def __init__(self, files: list[_HeadFile], checkpoint_seq: int | None,
                 report: LogReport) -> None:
        self.tree = CompactTree()
        self.checkpoint_id: str | None = None
        self._files, self._checkpoint_seq, self._report = files, checkpoint_seq, report
        # The first PROBLEMS_LISTED problems by their order (a heap: the latest on top, its
        # order negated), and how many later ones were only counted.
        self._held: list[tuple[tuple[int, int], str]] = []
        self.unlisted = 0
        self._late: list[_Anchor] = []
        self._newest: _Anchor | None = None
        for file in files:
            file.advance()
        self._due = 0
        self._check_due(0)

    def entry(self, seq: int, audit_id: str) -> None:
        self._report.last_audit_id = audit_id
        if seq == self._checkpoint_seq:
            self.checkpoint_id = audit_id
        if seq >= self._due:
            self._check_due(seq)

    def _check_due(self, size: int) -> None:
        root = self.tree.root()
        for file in self._files:
            while file.next is not None and file.next.head.tree_size <= size:
                if file.next.head.tree_size == size:
                    self._judge(file.next, root)
                else:
                    self._late.append(file.next)
                file.advance()
        self._due = min((f.next.head.tree_size for f in self._files if f.next is not None),
                        default=sys.maxsize)

    def finish(self, roots_at: Callable[[set[int]], dict[int, bytes]]) -> None:
        """After the scan: the heads naming more entries than it found valid, and the late
        ones (`roots_at(sizes)`: the log's roots at those sizes, all within its valid
        entries)."""
        entries = self._report.entries
        for file in self._files:
            while file.next is not None:
                anchor = file.next
                if anchor.head.tree_size > entries:
                    self._hold(anchor.order, (
                        f"{anchor.source}: {anchor.head.describe()} covers more entries than "
                        f"the log's {entries} valid ones: the log is truncated or damaged "
                        f"after seq {entries}"))
                else:
                    self._late.append(anchor)
                file.advance()
        if self._late:
            roots: dict[int, bytes] = roots_at({a.head.tree_size for a in self._late})
            for anchor in self._late:
                self._judge(anchor, roots[anchor.head.tree_size])

    def _judge(self, anchor: _Anchor, root: bytes) -> None:
        head = anchor.head
        if root != head.root:
            self._hold(anchor.order, (
                f"{anchor.source}: {head.describe()} has another root than the log's first "
                f"{head.tree_size} entries: the log was rewritten"))
            return
        if anchor.witnessed:
            self._report.witnessed += 1
        else:
            self._report.heads += 1
        newest = self._newest  # the largest; of those, the first in the files' order
        if newest is None or (head.tree_size, newest.order) > (newest.head.tree_size,
                                                                anchor.order):
            self._newest = anchor
            self._report.newest = head

    def _hold(self, order: tuple[int, int], problem: str) -> None:
        item = ((-order[0], -order[1]), problem)
        if len(self._held) < PROBLEMS_LISTED:
            heapq.heappush(self._held, item)
        else:
            self.unlisted += 1
            heapq.heappushpop(self._held, item)  # the latest of them goes

    def problems(self) -> list[str]:
        return [problem for _, problem in sorted(self._held, reverse=True)]


def _roots_at(fd: int | None, end: int, sizes: set[int]) -> dict[int, bytes]:
    """The roots of the log's first n lines for each n in `sizes`, hashed a line at a time."""
    tree = CompactTree()
    roots = {0: EMPTY_ROOT}
    lines = lines_forwards(fd, 0, end) if fd is not None else iter(())
    for _, line in itertools.islice(lines, max(sizes)):
        tree.append(leaf_hash(line))
        if tree.size in sizes:
            roots[tree.size] = tree.root()
    return roots


def _checkpoint(path: Path, pubkey: Ed25519PublicKey | None
                ) -> tuple[tuple[int, str] | None, list[str]]:
    cp_path = checkpoint_path(path)
    try:
        cp = read_checkpoint(cp_path, pubkey)
    except FileNotFoundError:
        return None, []
    except (OSError, ValueError) as exc:
        return None, [f"start-up checkpoint: {exc}"]
    return (cp.seq, cp.audit_id), []


def _checkpoint_holds(checkpoint: tuple[int, str], found: str | None,
                      report: LogReport) -> None:
    """`found`: the id of the log's valid entry at the checkpoint's seq, if it has one."""
    seq, audit_id = checkpoint
    if found is None:
        report.problems.append(f"start-up checkpoint names seq {seq}, beyond the log's "
                               f"{report.entries} valid entries: the log is truncated")
    elif found != audit_id:
        report.problems.append(f"start-up checkpoint names another entry at seq {seq}: the "
                               "log was rewritten")


def _notes(report: LogReport, pubkey: Ed25519PublicKey | None, anchored: bool,
           checkpoint: tuple[int, str] | None) -> None:
    if pubkey is None and anchored:
        report.notes.append("tree head signatures unchecked (no public key)")
    if not anchored and checkpoint is None:
        report.notes.append("no tree head, witness or checkpoint anchors this log: entries "
                            "removed from its end cannot be detected (see --witness)")
    elif report.newest is not None and report.newest.tree_size < report.entries:
        report.notes.append(f"{report.entries - report.newest.tree_size} entries after the "
                            "newest tree head")


# -- proofs ---------------------------------------------------------------------------------


class ProofError(AuditError):
    """A proof cannot be made, or does not verify."""


class _LogPass:
    """One pass over the log's complete lines, a chunk at a time (a proof's whole work, the
    log never held): the leaf hashes of the first `upto` (for `roots_of_ranges`); how many
    lines it has (`count`: up to `upto`, or all of them with `count_all`); its roots at
    `sizes`; the line at index `keep`."""

    def __init__(self, upto: int, sizes: set[int], keep: int | None = None, *,
                 count_all: bool = False) -> None:
        self._upto, self._sizes, self._keep, self._count_all = upto, sizes, keep, count_all
        self.count = 0
        self.roots = {0: EMPTY_ROOT}
        self.kept: bytes | None = None

    def proof(self, path: Path, ranges: list[tuple[int, int]]) -> list[bytes]:
        """The roots of `ranges` of the log's leaves (a proof's nodes), the pass made."""
        with open(path, "rb") as file:
            leaves = self._leaves(file.fileno(), _size(file.fileno()))
            nodes = roots_of_ranges(leaves, ranges)
            collections.deque(leaves, maxlen=0)  # the rest: counted, and rooted at `sizes`
        return nodes

    def _leaves(self, fd: int, end: int) -> Iterator[bytes]:
        tree = CompactTree()
        for _, line in lines_forwards(fd, 0, end):
            if self.count >= self._upto:
                if not self._count_all:
                    return
                self.count += 1
                continue
            if self.count == self._keep:
                self.kept = line
            self.count += 1
            leaf = leaf_hash(line)
            tree.append(leaf)
            if tree.size in self._sizes:
                self.roots[tree.size] = tree.root()
            yield leaf


def _heads(path: Path, pubkey: Ed25519PublicKey | None) -> Iterator[TreeHead]:
    """The log's valid tree heads (signed by `pubkey`, if given), read a line at a time."""
    try:
        with regular_file(tree_head_path(path)) as (fd, info):
            for _, head in HeadLines(fd, info.st_size):
                if isinstance(head, TreeHead) and (pubkey is None or signature_ok(head, pubkey)):
                    yield head
    except FileNotFoundError:
        return
    except ValueError as exc:  # (a FIFO, which would never end)
        raise ProofError(f"cannot read tree heads: {exc}") from exc


def prove_inclusion(path: Path, seq: int, pubkey: Ed25519PublicKey | None,
                    tree_size: int | None = None) -> dict[str, Any]:
    """An inclusion proof of entry `seq` against the newest tree head (or the head of
    `tree_size`), checked against the log before it is handed out."""
    head: TreeHead | None = None  # the newest; of those, the first in the file
    for found in _heads(path, pubkey):
        if tree_size is not None and found.tree_size != tree_size:
            continue
        if head is None or (found.tree_size, found.timestamp_ms) > (head.tree_size,
                                                                    head.timestamp_ms):
            head = found
    if head is None:
        raise ProofError(f"no {'signed ' if pubkey else ''}tree head"
                         f"{f' of size {tree_size}' if tree_size is not None else ''} "
                         f"beside {path}")
    if seq < 1:  # a 0-based index, most likely
        raise ProofError(f"seq {seq}: entries are counted from 1 (the first is seq 1)")
    if seq > head.tree_size:
        raise ProofError(f"seq {seq} is not covered by the {head.describe()}")
    log = _LogPass(head.tree_size, {head.tree_size}, keep=seq - 1)
    path_nodes = log.proof(path, inclusion_ranges(seq - 1, head.tree_size))
    _same_root(log.count, log.roots.get(head.tree_size), head)
    assert log.kept is not None  # (seq <= tree_size <= count)
    return {
        "seq": seq, "leaf_index": seq - 1, "entry": log.kept.decode(),
        "leaf_hash": leaf_hash(log.kept).hex(),
        "inclusion_path": [h.hex() for h in path_nodes],
        "tree_head": msgspec.to_builtins(head),
    }


def _same_root(count: int, root: bytes | None, head: TreeHead) -> None:
    """`count`: the log's entries (at least those of the head's size); `root`: its root at
    the head's size."""
    if count < head.tree_size or root is None:
        raise ProofError(f"the log holds {count} entries, less than the "
                         f"{head.describe()}: truncated")
    if root != head.root:
        raise ProofError(f"the log's first {head.tree_size} entries do not have the root of "
                         f"the {head.describe()}")


def _proof_head(value: Any) -> TreeHead:
    """A proof's tree head; raises ValueError (or msgspec's) unless its root is 32 bytes of
    hex (`TreeHead.root` would raise on the proof's check, outside the document's)."""
    head = msgspec.convert(value, TreeHead)
    if len(head.root) != 32:
        raise ValueError(f"root_hash {head.root_hash!r} is not 32 bytes")
    return head


def check_inclusion(doc: Any, pubkey: Ed25519PublicKey) -> str:
    """Verify an inclusion proof document; returns what it proves, raises ProofError."""
    try:
        head = _proof_head(doc["tree_head"])
        entry: str = doc["entry"]
        seq = int(doc["seq"])
        index = int(doc["leaf_index"])
        path = [bytes.fromhex(h) for h in doc["inclusion_path"]]
        claimed_leaf = bytes.fromhex(doc["leaf_hash"])
        entry_seq = msgspec.json.decode(entry.encode()).get("seq")
    except (KeyError, TypeError, ValueError, AttributeError, msgspec.MsgspecError) as exc:
        raise ProofError(f"not an inclusion proof: {exc}") from exc
    if not signature_ok(head, pubkey):
        raise ProofError(f"the {head.describe()} is not signed by this key")
    leaf = leaf_hash(entry.encode())
    if leaf != claimed_leaf or index != seq - 1 or entry_seq != seq:
        raise ProofError("the entry, its seq and its leaf do not agree")
    if not verify_inclusion(leaf, index, head.tree_size, path, head.root):
        raise ProofError(f"entry {seq} is not in the {head.describe()}")
    return f"entry {seq} is in the {head.describe()}, root {head.root_hash}"


def prove_consistency(path: Path, old: int, new: int | None,
                      pubkey: Ed25519PublicKey | None) -> dict[str, Any]:
    """A consistency proof between the log's first `old` and first `new` entries (`new`
    defaults to the newest tree head), with the signed heads of those sizes when there are."""
    at_old: TreeHead | None = None  # the last head of size old
    at_new: TreeHead | None = None  # the last of size new (or of the largest size)
    for head in _heads(path, pubkey):
        if head.tree_size == old:
            at_old = head
        if head.tree_size == new or (new is None and (
                at_new is None or head.tree_size >= at_new.tree_size)):
            at_new = head
    if new is None:
        if at_new is None:
            raise ProofError(f"no tree head beside {path}: give NEW")
        new = at_new.tree_size
    by_size = {h.tree_size: h for h in (at_old, at_new) if h is not None}
    sizes_ok = 0 <= old <= new
    log = _LogPass(new if sizes_ok else 0, {old, new}, count_all=True)
    nodes = log.proof(path, consistency_ranges(old, new) if sizes_ok else [])
    if not sizes_ok or new > log.count:
        raise ProofError(f"sizes must be 0 <= OLD <= NEW <= {log.count} (the log's entries)")
    for size in (old, new):
        if size in by_size:
            _same_root(new, log.roots[size], by_size[size])
    return {
        "old_size": old, "new_size": new,
        "old_root": log.roots[old].hex(), "new_root": log.roots[new].hex(),
        "consistency_path": [h.hex() for h in nodes],
        "old_tree_head": msgspec.to_builtins(by_size[old]) if old in by_size else None,
        "new_tree_head": msgspec.to_builtins(by_size[new]) if new in by_size else None,
    }


def check_consistency(doc: Any, pubkey: Ed25519PublicKey | None) -> str:
    """Verify a consistency proof document (and, with a key, the tree heads it carries)."""
    try:
        old, new = int(doc["old_size"]), int(doc["new_size"])
        old_root, new_root = bytes.fromhex(doc["old_root"]), bytes.fromhex(doc["new_root"])
        path = [bytes.fromhex(h) for h in doc["consistency_path"]]
        heads = [(size, root, None if doc.get(k) is None else _proof_head(doc[k]))
                 for size, root, k in ((old, old_root, "old_tree_head"),
                                       (new, new_root, "new_tree_head"))]
    except (KeyError, TypeError, ValueError, AttributeError, msgspec.MsgspecError) as exc:
        raise ProofError(f"not a consistency proof: {exc}") from exc
    for size, root, head in heads:
        if head is None:
            continue
        if head.tree_size != size or head.root != root:
            raise ProofError(f"the {head.describe()} does not match size {size} and its root")
        if pubkey is not None and not signature_ok(head, pubkey):
            raise ProofError(f"the {head.describe()} is not signed by this key")
    if not verify_consistency(old, new, old_root, new_root, path):
        raise ProofError(f"the tree of {new} entries does not extend the tree of {old}")
    signed = sum(h is not None for _, _, h in heads)
    return (f"the tree of {new} entries extends the tree of {old} "
            f"({signed} of the 2 roots from signed tree heads"
            f"{'' if pubkey is not None or not signed else ', signatures unchecked'})")
