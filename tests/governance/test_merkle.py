"""RFC 6962 Merkle hashing: the CT reference vectors, and proofs that verify for every size and
fail on any tamper."""

from __future__ import annotations

import hashlib

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rcan_rtps.governance.merkle import (
    EMPTY_ROOT,
    CompactTree,
    consistency_proof,
    inclusion_proof,
    leaf_hash,
    root_of,
    verify_consistency,
    verify_inclusion,
)

# The test tree of the Certificate Transparency reference implementation (RFC 6962): its eight
# leaves and the published root of each prefix, and some of its published proofs.
CT_LEAVES = [bytes.fromhex(h) for h in (
    "", "00", "10", "2021", "3031", "40414243", "5051525354555657",
    "606162636465666768696a6b6c6d6e6f")]
CT_ROOTS = [bytes.fromhex(h) for h in (
    "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "6e340b9cffb37a989ca544e6bb780a2c78901d3fb33738768511a30617afa01d",
    "fac54203e7cc696cf0dfcb42c92a1d9dbaf70ad9e621f4bd8d98662f00e3c125",
    "aeb6bcfe274b70a14fb067a5e5578264db0fa9b51af5e0ba159158f329e06e77",
    "d37ee418976dd95753c1c73862b9398fa2a2cf9b4ff0fdfe8b30cd95209614b7",
    "4e3bbb1f7b478dcfe71fb631631519a3bca12c9aefca1612bfce4c13a86264d4",
    "76e67dadbcdf1e10e1b74ddc608abd2f98dfb16fbce75277b5232a127f2087ef",
    "ddb89be403809e325750d3d263cd78929c2942b7942a34b77e122c9594a74c8c",
    "5dc9da79a70659a9ad559cb701ded9a2ab9d823aad2f4960cfe370eff4604328")]
CT_INCLUSION = [
    (0, 8, ["96a296d224f285c67bee93c30f8a309157f0daa35dc5b87e410b78630a09cfc7",
            "5f083f0a1a33ca076a95279832580db3e0ef4584bdff1f54c8a360f50de3031e",
            "6b47aaf29ee3c2af9af889bc1fb9254dabd31177f16232dd6aab035ca39bf6e4"]),
    (5, 8, ["bc1a0643b12e4d2d7c77918f44e0f4f79a838b6cf9ec5b5c283e1f4d88599e6b",
            "ca854ea128ed050b41b35ffc1b87b8eb2bde461e9e3b5596ece6b9d5975a0ae0",
            "d37ee418976dd95753c1c73862b9398fa2a2cf9b4ff0fdfe8b30cd95209614b7"]),
]
CT_CONSISTENCY = [
    (2, 8, ["5f083f0a1a33ca076a95279832580db3e0ef4584bdff1f54c8a360f50de3031e",
            "6b47aaf29ee3c2af9af889bc1fb9254dabd31177f16232dd6aab035ca39bf6e4"]),
    (6, 8, ["0ebc5d3437fbe2db158b9f126a1d118e308181031d0a949f8dededebc558ef6a",
            "ca854ea128ed050b41b35ffc1b87b8eb2bde461e9e3b5596ece6b9d5975a0ae0",
            "d37ee418976dd95753c1c73862b9398fa2a2cf9b4ff0fdfe8b30cd95209614b7"]),
    (2, 5, ["5f083f0a1a33ca076a95279832580db3e0ef4584bdff1f54c8a360f50de3031e",
            "bc1a0643b12e4d2d7c77918f44e0f4f79a838b6cf9ec5b5c283e1f4d88599e6b"]),
]
HASHES = [leaf_hash(d) for d in CT_LEAVES]


def test_roots_match_the_ct_reference_tree() -> None:
    assert EMPTY_ROOT == CT_ROOTS[0] == root_of([])
    tree = CompactTree()
    for n, leaf in enumerate(HASHES, start=1):
        tree.append(leaf)
        assert tree.root() == CT_ROOTS[n] == root_of(HASHES[:n])
    # The prefixes: a leaf is 0x00-prefixed, a node 0x01-prefixed.
    assert HASHES[0] == hashlib.sha256(b"\x00").digest()
    assert CT_ROOTS[2] == hashlib.sha256(b"\x01" + HASHES[0] + HASHES[1]).digest()


@pytest.mark.parametrize(("index", "size", "proof"), CT_INCLUSION)
def test_inclusion_proofs_match_the_ct_reference(index: int, size: int, proof: list[str]) -> None:
    want = [bytes.fromhex(h) for h in proof]
    assert inclusion_proof(HASHES, index, size) == want
    assert verify_inclusion(HASHES[index], index, size, want, CT_ROOTS[size])


@pytest.mark.parametrize(("old", "new", "proof"), CT_CONSISTENCY)
def test_consistency_proofs_match_the_ct_reference(old: int, new: int, proof: list[str]) -> None:
    want = [bytes.fromhex(h) for h in proof]
    assert consistency_proof(HASHES, old, new) == want
    assert verify_consistency(old, new, CT_ROOTS[old], CT_ROOTS[new], want)


def test_a_compact_tree_restored_from_its_peaks_goes_on_alike() -> None:
    leaves = [leaf_hash(bytes([i])) for i in range(70)]
    whole = CompactTree()
    whole.extend(leaves[:37])
    resumed = CompactTree(whole.size, whole.peaks)
    whole.extend(leaves[37:])
    resumed.extend(leaves[37:])
    assert resumed.root() == whole.root() == root_of(leaves)
    assert len(whole.peaks) == bin(70).count("1")
    with pytest.raises(ValueError):
        CompactTree(5, whole.peaks)


def _leaves(n: int) -> list[bytes]:
    return [leaf_hash(i.to_bytes(4, "big")) for i in range(n)]


def _flip(proof: list[bytes], which: int, bit: int) -> list[bytes]:
    bad = list(proof)
    h = bytearray(bad[which])
    h[bit // 8] ^= 1 << (bit % 8)
    bad[which] = bytes(h)
    return bad


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_inclusion_proofs_verify_and_fail_on_any_tamper(data: st.DataObject) -> None:
    size = data.draw(st.integers(1, 300), label="size")
    index = data.draw(st.integers(0, size - 1), label="index")
    leaves = _leaves(size)
    root = root_of(leaves)
    proof = inclusion_proof(leaves, index, size)
    assert verify_inclusion(leaves[index], index, size, proof, root)
    if proof:
        which = data.draw(st.integers(0, len(proof) - 1))
        bit = data.draw(st.integers(0, 255))
        assert not verify_inclusion(leaves[index], index, size, _flip(proof, which, bit), root)
        assert not verify_inclusion(leaves[index], index, size, proof[:-1], root)
    assert not verify_inclusion(leaves[index], index, size, [*proof, root], root)
    other = data.draw(st.integers(0, size).filter(lambda i: i != index), label="wrong index")
    assert not verify_inclusion(leaves[index], other, size, proof, root)
    # Against another tree head (a size and the root of that size): RFC 9162 proofs bind the
    # size through the root, so a size is only ever checked with its own signed root.
    wrong = data.draw(st.integers(index + 1, 300).filter(lambda s: s != size), label="wrong size")
    assert not verify_inclusion(leaves[index], index, wrong, proof, root_of(_leaves(wrong)))
    assert not verify_inclusion(leaf_hash(b"x"), index, size, proof, root)
    assert not verify_inclusion(leaves[index], index, size, proof, _flip([root], 0, 0)[0])


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_consistency_proofs_verify_and_fail_on_any_tamper(data: st.DataObject) -> None:
    new = data.draw(st.integers(1, 300), label="new")
    old = data.draw(st.integers(0, new), label="old")
    leaves = _leaves(new)
    old_root, new_root = root_of(leaves[:old]), root_of(leaves)
    proof = consistency_proof(leaves, old, new)
    assert verify_consistency(old, new, old_root, new_root, proof)
    if proof:
        which = data.draw(st.integers(0, len(proof) - 1))
        bit = data.draw(st.integers(0, 255))
        assert not verify_consistency(old, new, old_root, new_root, _flip(proof, which, bit))
        assert not verify_consistency(old, new, old_root, new_root, proof[:-1])
    assert not verify_consistency(old, new, old_root, new_root, [*proof, new_root])
    wrong_old = data.draw(st.integers(0, new).filter(lambda s: s != old), label="wrong old")
    assert not verify_consistency(wrong_old, new, old_root, new_root, proof)
    if old:  # anything extends the empty tree
        wrong_new = data.draw(st.integers(old, 300).filter(lambda s: s != new), label="wrong new")
        assert not verify_consistency(old, wrong_new, old_root, root_of(_leaves(wrong_new)),
                                      proof)
    assert not verify_consistency(old, new, _flip([old_root], 0, 3)[0], new_root, proof)
    if old:  # every tree extends the empty one: nothing more to tamper with then
        assert not verify_consistency(old, new, old_root, _flip([new_root], 0, 9)[0], proof)
        # A tree that is not an extension: one leaf of the old part changed.
        forked = list(leaves)
        forked[data.draw(st.integers(0, old - 1))] = leaf_hash(b"forged")
        assert not verify_consistency(old, new, old_root, root_of(forked),
                                      consistency_proof(forked, old, new))
