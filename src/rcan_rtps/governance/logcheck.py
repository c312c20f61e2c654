"""Checking an audit log against what anchors it, and proofs over it (`rcan-rtps audit ...`).

`check_log` verifies the chain (links, hashes, canonical form, signatures when a key is given)
and then every anchor: the tree heads in `<log>.sth`, those of witness files, and the start-up
checkpoint. A head must be signed by the key and its root must be the root of the log's first
`tree_size` entries; a head (or checkpoint) naming more entries than the log holds means the
log was truncated, and is reported by name. Proofs are RFC 9162 inclusion and consistency
proofs, built from the log's lines (the leaf of entry `seq` is its line without the newline).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from ._durable import read_regular
from .audit import checkpoint_path, entries, read_checkpoint
from .errors import AuditError, AuditIntegrityError
from .merkle import (
    EMPTY_ROOT,
    CompactTree,
    consistency_proof,
    inclusion_proof,
    leaf_hash,
    verify_consistency,
    verify_inclusion,
)
from .treehead import (
    BadTreeHead,
    TreeHead,
    parse_tree_heads,
    signature_ok,
    tree_head_path,
)


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


def check_log(path: Path, pubkey: Ed25519PublicKey | None,
              witness_files: Sequence[Path] = (), *, live: bool = False) -> LogReport:
    """Everything `audit verify` checks. Raises OSError only when the log cannot be read and
    nothing anchors it (then there is nothing to check).

    `live`: the log of a running bridge. Its tree heads are read before its entries (a head is
    written only once its entries are durable, so every head read names entries on disk), and
    a last line still being appended is not an entry yet."""
    report = LogReport()
    anchors = _anchors(tree_head_path(path), "tree heads", pubkey, report)
    own = len(anchors)
    for witness in witness_files:
        if not witness.exists():
            report.problems.append(f"witness file {witness} does not exist")
            continue
        anchors += _anchors(witness, f"witness {witness}", pubkey, report)
    checkpoint = _checkpoint(path, pubkey, report)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        if not anchors and checkpoint is None:
            raise
        report.problems.append(f"{path} is missing, but tree heads or a checkpoint name its "
                               "entries")
        data = b""
    if live:
        data = data[: data.rfind(b"\n") + 1]
    roots, ids = _scan(data, pubkey, {a.head.tree_size for a in anchors},
                       checkpoint[0] if checkpoint else None, report)
    for i, anchor in enumerate(anchors):
        if _anchor_holds(anchor, roots, report):
            if i < own:
                report.heads += 1
            else:
                report.witnessed += 1
            if report.newest is None or anchor.head.tree_size > report.newest.tree_size:
                report.newest = anchor.head
    if checkpoint is not None:
        _checkpoint_holds(checkpoint, ids, report)
    _notes(report, pubkey, anchors, checkpoint)
    return report


def _anchors(file: Path, source: str, pubkey: Ed25519PublicKey | None,
             report: LogReport) -> list[_Anchor]:
    try:
        data = read_regular(file)
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as exc:  # (ValueError: a FIFO, say, which would never end)
        report.problems.append(f"{source}: cannot read {file}: {exc}")
        return []
    heads, torn = parse_tree_heads(data)
    if torn:
        report.notes.append(f"{source}: an incomplete last line ignored ({len(torn)} bytes; "
                            "a crash while it was written)")
    out = []
    for n, head in enumerate(heads, start=1):
        if isinstance(head, BadTreeHead):
            report.problems.append(f"{source} line {head.line_no}: {head.problem}")
        elif pubkey is not None and not signature_ok(head, pubkey):
            report.problems.append(f"{source} line {n}: {head.describe()} has a bad signature")
        else:
            out.append(_Anchor(f"{source} line {n}", head))
    return out


def _checkpoint(path: Path, pubkey: Ed25519PublicKey | None,
                report: LogReport) -> tuple[int, str] | None:
    cp_path = checkpoint_path(path)
    try:
        cp = read_checkpoint(cp_path, pubkey)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        report.problems.append(f"start-up checkpoint: {exc}")
        return None
    return cp.seq, cp.audit_id


def _scan(data: bytes, pubkey: Ed25519PublicKey | None, sizes: set[int],
          checkpoint_seq: int | None, report: LogReport
          ) -> tuple[dict[int, bytes], dict[int, str]]:
    """Verify the chain; the root at each size in `sizes`, the id at the checkpoint's seq."""
    tree = CompactTree()
    roots: dict[int, bytes] = {0: EMPTY_ROOT}
    ids: dict[int, str] = {}
    try:
        for seq, audit_id, line in entries(data, pubkey):
            tree.append(leaf_hash(line))
            report.last_audit_id = audit_id
            if seq in sizes:
                roots[seq] = tree.root()
            if seq == checkpoint_seq:
                ids[seq] = audit_id
    except AuditIntegrityError as exc:
        report.problems.append(str(exc))
        report.bad_seq = exc.seq
    report.entries = tree.size
    return roots, ids


def _anchor_holds(anchor: _Anchor, roots: dict[int, bytes], report: LogReport) -> bool:
    head = anchor.head
    root = roots.get(head.tree_size)
    if root is None:
        report.problems.append(
            f"{anchor.source}: {head.describe()} covers more entries than the log's "
            f"{report.entries} valid ones: the log is truncated or damaged after seq "
            f"{report.entries}")
        return False
    if root != head.root:
        report.problems.append(f"{anchor.source}: {head.describe()} has another root than the "
                               f"log's first {head.tree_size} entries: the log was rewritten")
        return False
    return True


def _checkpoint_holds(checkpoint: tuple[int, str], ids: dict[int, str],
                      report: LogReport) -> None:
    seq, audit_id = checkpoint
    if seq not in ids:
        report.problems.append(f"start-up checkpoint names seq {seq}, beyond the log's "
                               f"{report.entries} valid entries: the log is truncated")
    elif ids[seq] != audit_id:
        report.problems.append(f"start-up checkpoint names another entry at seq {seq}: the "
                               "log was rewritten")


def _notes(report: LogReport, pubkey: Ed25519PublicKey | None, anchors: list[_Anchor],
           checkpoint: tuple[int, str] | None) -> None:
    if pubkey is None and anchors:
        report.notes.append("tree head signatures unchecked (no public key)")
    if not anchors and checkpoint is None:
        report.notes.append("no tree head, witness or checkpoint anchors this log: entries "
                            "removed from its end cannot be detected (see --witness)")
    elif report.newest is not None and report.newest.tree_size < report.entries:
        report.notes.append(f"{report.entries - report.newest.tree_size} entries after the "
                            "newest tree head")


# -- proofs ---------------------------------------------------------------------------------


class ProofError(AuditError):
    """A proof cannot be made, or does not verify."""


def _lines_of(path: Path) -> list[bytes]:
    data = path.read_bytes()
    return data.split(b"\n")[:-1]  # complete lines only


def _heads(path: Path, pubkey: Ed25519PublicKey | None) -> list[TreeHead]:
    try:
        parsed, _ = parse_tree_heads(tree_head_path(path).read_bytes())
    except FileNotFoundError:
        return []
    return [h for h in parsed if isinstance(h, TreeHead)
            and (pubkey is None or signature_ok(h, pubkey))]


def prove_inclusion(path: Path, seq: int, pubkey: Ed25519PublicKey | None,
                    tree_size: int | None = None) -> dict[str, Any]:
    """An inclusion proof of entry `seq` against the newest tree head (or the head of
    `tree_size`), checked against the log before it is handed out."""
    heads = _heads(path, pubkey)
    if tree_size is not None:
        heads = [h for h in heads if h.tree_size == tree_size]
    if not heads:
        raise ProofError(f"no {'signed ' if pubkey else ''}tree head"
                         f"{f' of size {tree_size}' if tree_size is not None else ''} "
                         f"beside {path}")
    head = max(heads, key=lambda h: (h.tree_size, h.timestamp_ms))
    if seq < 1:  # a 0-based index, most likely
        raise ProofError(f"seq {seq}: entries are counted from 1 (the first is seq 1)")
    if seq > head.tree_size:
        raise ProofError(f"seq {seq} is not covered by the {head.describe()}")
    leaves = [leaf_hash(line) for line in _lines_of(path)[:head.tree_size]]
    _same_root(leaves, head)
    line = _lines_of(path)[seq - 1]
    return {
        "seq": seq, "leaf_index": seq - 1, "entry": line.decode(),
        "leaf_hash": leaves[seq - 1].hex(),
        "inclusion_path": [h.hex() for h in inclusion_proof(leaves, seq - 1, head.tree_size)],
        "tree_head": msgspec.to_builtins(head),
    }


def _same_root(leaves: list[bytes], head: TreeHead) -> None:
    if len(leaves) < head.tree_size:
        raise ProofError(f"the log holds {len(leaves)} entries, less than the "
                         f"{head.describe()}: truncated")
    tree = CompactTree()
    tree.extend(leaves[:head.tree_size])
    if tree.root() != head.root:
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
    heads = _heads(path, pubkey)
    if new is None:
        if not heads:
            raise ProofError(f"no tree head beside {path}: give NEW")
        new = max(h.tree_size for h in heads)
    lines = _lines_of(path)
    if not 0 <= old <= new <= len(lines):
        raise ProofError(f"sizes must be 0 <= OLD <= NEW <= {len(lines)} (the log's entries)")
    leaves = [leaf_hash(line) for line in lines[:new]]
    by_size = {h.tree_size: h for h in heads}
    roots = {}
    for size in (old, new):
        tree = CompactTree()
        tree.extend(leaves[:size])
        roots[size] = tree.root()
        if size in by_size:
            _same_root(leaves, by_size[size])
    return {
        "old_size": old, "new_size": new,
        "old_root": roots[old].hex(), "new_root": roots[new].hex(),
        "consistency_path": [h.hex() for h in consistency_proof(leaves, old, new)],
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
