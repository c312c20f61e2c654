"""RFC 6962 / RFC 9162 Merkle tree hashing: tree heads, inclusion and consistency proofs.

Leaves are hashed SHA-256(0x00 || data), interior nodes SHA-256(0x01 || left || right), and a
tree of n leaves splits at the largest power of two below n (RFC 9162 §2.1.1), so roots and
proofs agree with any Certificate Transparency implementation (checked against the CT
reference vectors in the tests).

`CompactTree` is what a writer keeps: one hash per set bit of the tree size (the roots of the
perfect subtrees the leaves fill from the left), O(log n) memory, O(1) amortised hashes per
appended leaf and O(log n) for the root. A proof is the roots of disjoint ranges of leaves,
known from the sizes alone (`inclusion_ranges`, `consistency_ranges`): they are computed in one
pass over the leaves (`roots_of_ranges`), a log read a line at a time, never held. Checking a
proof needs only the proof, the sizes and the roots.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence

HASH_SIZE = 32
EMPTY_ROOT = hashlib.sha256(b"").digest()


def leaf_hash(data: bytes) -> bytes:
    return hashlib.sha256(b"\x00" + data).digest()


def node_hash(left: bytes, right: bytes) -> bytes:
    return hashlib.sha256(b"\x01" + left + right).digest()


def _split(n: int) -> int:
    """The largest power of two strictly below n (n >= 2)."""
    return 1 << ((n - 1).bit_length() - 1)


class CompactTree:
    """The right edge of a Merkle tree: enough to append leaves and compute the root."""

    __slots__ = ("_peaks", "size")

    def __init__(self, size: int = 0, peaks: Sequence[bytes] = ()) -> None:
        if len(peaks) != bin(size).count("1") or any(len(p) != HASH_SIZE for p in peaks):
            raise ValueError(f"a tree of {size} leaves has {bin(size).count('1')} peaks, "
                             f"not {len(peaks)}")
        self.size = size
        self._peaks = list(peaks)  # largest subtree first

    @property
    def peaks(self) -> tuple[bytes, ...]:
        return tuple(self._peaks)

    def copy(self) -> CompactTree:
        return CompactTree(self.size, self._peaks)

    def append(self, leaf: bytes) -> None:
        """Add one leaf hash; merges the perfect subtrees it completes."""
        node, below = leaf, self.size
        while below & 1:
            node = node_hash(self._peaks.pop(), node)
            below >>= 1
        self._peaks.append(node)
        self.size += 1

    def extend(self, leaves: Iterable[bytes]) -> None:
        for leaf in leaves:
            self.append(leaf)

    def root(self) -> bytes:
        if not self._peaks:
            return EMPTY_ROOT
        node = self._peaks[-1]
        for peak in reversed(self._peaks[:-1]):
            node = node_hash(peak, node)
        return node


def root_of(leaves: Sequence[bytes]) -> bytes:
    """MTH over leaf hashes (RFC 9162 §2.1.1)."""
    tree = CompactTree()
    tree.extend(leaves)
    return tree.root()


def inclusion_proof(leaves: Sequence[bytes], index: int, size: int) -> list[bytes]:
    """PATH(index, D[size]) of RFC 9162 §2.1.3.1, over the first `size` leaf hashes."""
    if not 0 <= index < size <= len(leaves):
        raise ValueError(f"no leaf {index} in a tree of {size}")
    return roots_of_ranges(leaves, inclusion_ranges(index, size))


def inclusion_ranges(index: int, size: int) -> list[tuple[int, int]]:
    """The leaf ranges [lo, hi) whose roots are PATH(index, D[size]), in the proof's order:
    what the proof needs, known from the two numbers alone (0 <= index < size)."""
    ranges: list[tuple[int, int]] = []
    lo, hi = 0, size
    while hi - lo > 1:
        k = _split(hi - lo)
        if index < lo + k:
            ranges.append((lo + k, hi))
            hi = lo + k
        else:
            ranges.append((lo, lo + k))
            lo += k
    return ranges[::-1]  # the recursion's innermost sibling comes first


def consistency_proof(leaves: Sequence[bytes], old: int, new: int) -> list[bytes]:
    """PROOF(old, D[new]) of RFC 9162 §2.1.4.1 (empty when old is 0 or old == new)."""
    if not 0 <= old <= new <= len(leaves):
        raise ValueError(f"no consistency proof from {old} to {new} leaves")
    return roots_of_ranges(leaves, consistency_ranges(old, new))


def consistency_ranges(old: int, new: int) -> list[tuple[int, int]]:
    """The leaf ranges [lo, hi) whose roots are PROOF(old, D[new]), in the proof's order
    (none when old is 0 or old == new; 0 <= old <= new)."""
    if old in (0, new):
        return []
    ranges: list[tuple[int, int]] = []
    lo, hi, m, whole = 0, new, old, True
    while m != hi - lo:
        k = _split(hi - lo)
        if m <= k:
            ranges.append((lo + k, hi))
            hi = lo + k
        else:
            ranges.append((lo, lo + k))
            lo, m, whole = lo + k, m - k, False
    if not whole:
        ranges.append((lo, hi))
    return ranges[::-1]


def roots_of_ranges(leaves: Iterable[bytes], ranges: Sequence[tuple[int, int]]) -> list[bytes]:
    """The root of each of `ranges` (disjoint [lo, hi) of leaf indexes), in their order, from
    one pass over `leaves` that stops after the last range: a proof made from a log read a
    line at a time holds O(log² n) hashes, never the leaves. A range the leaves end in has
    the root of the part they reach (callers check the count first)."""
    order = sorted(range(len(ranges)), key=lambda i: ranges[i][0])
    roots = [EMPTY_ROOT] * len(ranges)
    if not order:
        return roots
    pending = iter(order)
    current = next(pending)
    tree = CompactTree()
    for index, leaf in enumerate(leaves):
        lo, hi = ranges[current]
        if index < lo:
            continue
        tree.append(leaf)
        if index + 1 == hi:
            roots[current], tree = tree.root(), CompactTree()
            following = next(pending, None)
            if following is None:
                return roots
            current = following
    if tree.size:
        roots[current] = tree.root()
    return roots


def verify_inclusion(leaf: bytes, index: int, size: int, proof: Sequence[bytes],
                     root: bytes) -> bool:
    """RFC 9162 §2.1.3.2: does `proof` place `leaf` at `index` in the tree of `size`/`root`?"""
    if not 0 <= index < size or not _hashes_ok([leaf, root, *proof]):
        return False
    fn, sn, node = index, size - 1, leaf
    for sibling in proof:
        if sn == 0:
            return False
        if fn & 1 or fn == sn:
            node = node_hash(sibling, node)
            while not fn & 1 and fn:
                fn, sn = fn >> 1, sn >> 1
        else:
            node = node_hash(node, sibling)
        fn, sn = fn >> 1, sn >> 1
    return sn == 0 and node == root


def verify_consistency(old: int, new: int, old_root: bytes, new_root: bytes,
                       proof: Sequence[bytes]) -> bool:
    """RFC 9162 §2.1.4.2: is the tree `new`/`new_root` an append-only extension of
    `old`/`old_root`? (old 0: only the empty root; old == new: same root, empty proof.)"""
    if not 0 <= old <= new or not _hashes_ok([old_root, new_root, *proof]):
        return False
    if old == 0:  # the empty tree: every tree extends it
        return old_root == EMPTY_ROOT and not proof and (new > 0 or new_root == EMPTY_ROOT)
    if old == new:
        return old_root == new_root and not proof
    if not proof:
        return False
    path = list(proof)
    if old & (old - 1) == 0:  # a power of two: the old tree is a subtree the proof leaves out
        path.insert(0, old_root)
    fn, sn = old - 1, new - 1
    while fn & 1:
        fn, sn = fn >> 1, sn >> 1
    fr = sr = path[0]
    for node in path[1:]:
        if sn == 0:
            return False
        if fn & 1 or fn == sn:
            fr, sr = node_hash(node, fr), node_hash(node, sr)
            while not fn & 1 and fn:
                fn, sn = fn >> 1, sn >> 1
        else:
            sr = node_hash(sr, node)
        fn, sn = fn >> 1, sn >> 1
    return sn == 0 and fr == old_root and sr == new_root


def _hashes_ok(hashes: Iterable[bytes]) -> bool:
    return all(isinstance(h, bytes) and len(h) == HASH_SIZE for h in hashes)
