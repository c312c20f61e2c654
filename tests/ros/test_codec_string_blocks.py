"""Sequences of strings are encoded as one block, kept by its tuple of strings (a robot's
joint names are the same in every JointState). Against cyclonedds' own codec: names of every
length mod 4 (the padding between them), non-ASCII, a second list after the first, lists
after a field that leaves the buffer unaligned; fixed arrays and bounded sequences of
strings keep their own path; bad items in a plain list are still named, never crash.
Decoders keep the last block of each count too: the list they give is the caller's, a
truncated sample's block is never kept, and a hostile stream of counts keeps a few."""

from __future__ import annotations

from typing import Any

import pytest

from rcan_rtps.ros.errors import CdrDecodeError, ValueFitError
from rcan_rtps.ros.serialization import Codec, default_codec
from rcan_rtps.ros.typesys import cdr, cdr_decode

pytestmark = pytest.mark.offline

JOINTS = "sensor_msgs/msg/JointState"


def joint_state(names: list[str]) -> dict[str, Any]:
    n = len(names)
    return {"header": {"stamp": {"sec": 3, "nanosec": 4}, "frame_id": "b"}, "name": names,
            "position": [0.5] * n, "velocity": [], "effort": [1.0] * n}


def both_ways(type_name: str, value: dict[str, Any]) -> bytes:
    """Plain and typed encodings, each twice (built, then found), all as cyclonedds'."""
    codec = default_codec()
    message = codec.values.build(type_name, value)
    expected = bytes(message.serialize())
    generated = codec.of(type_name)
    for _ in range(2):
        assert generated.encode_plain(value) == expected
        assert generated.encode(message) == expected
    assert codec.deserialize(type_name, expected, plain=True) == codec.values.to_plain(
        type_name, message)
    return expected


NAMES = [[], [""], ["a"], ["ab", "abc", "abcd", "abcde"], ["gelenk_ä", "关节", "joint_🤖"],
         [f"joint_{i}" for i in range(12)]]


@pytest.mark.parametrize("names", NAMES, ids=[str(len(n)) for n in NAMES])
def test_joint_names_encode_as_cyclonedds_does(names: list[str]) -> None:
    both_ways(JOINTS, joint_state(names))


def test_another_list_after_the_first_is_its_own() -> None:
    first = both_ways(JOINTS, joint_state(["left", "right"]))
    second = both_ways(JOINTS, joint_state(["left", "rihgt"]))
    assert first != second
    codec = default_codec()
    assert codec.deserialize(JOINTS, second, plain=True)["name"] == ["left", "rihgt"]


def test_a_tuple_of_names_is_the_list() -> None:
    codec = default_codec()
    message = codec.values.build(JOINTS, joint_state(["x", "yy"]))
    listed = codec.of(JOINTS).encode(message)
    message.name = ("x", "yy")
    assert codec.of(JOINTS).encode(message) == listed


@pytest.mark.parametrize("type_name", ["test_msgs/msg/Arrays", "test_msgs/msg/BoundedSequences",
                                       "test_msgs/msg/UnboundedSequences"])
@pytest.mark.parametrize("first", range(4))
def test_strings_after_fields_of_every_length(type_name: str, first: int) -> None:
    # byte_values come before the strings: with 0..3 of them (a fixed array: always 3) the
    # strings' lengths start at every residue mod 4; a string[3] array has no count before it
    octets = 3 if type_name.endswith("Arrays") else first
    both_ways(type_name, {"byte_values": bytes(range(octets)),
                          "string_values": ["s" * (first + 1), "", "tt"]})


@pytest.mark.parametrize(("names", "path"), [(["ok", 5], "name[1]"), (["ok", {"a": 1}], "name[1]"),
                                             (["ok", None], "name[1]")])
def test_a_bad_name_is_named_even_after_good_lists(names: list[Any], path: str) -> None:
    both_ways(JOINTS, joint_state(["ok", "fine"]))
    with pytest.raises(ValueFitError, match=path.replace("[", r"\[")):
        default_codec().serialize(JOINTS, joint_state(names))


def test_the_kept_blocks_are_bounded() -> None:
    generated = default_codec().of(JOINTS)
    for i in range(3 * cdr.STRING_BLOCKS_KEPT):
        generated.encode_plain(joint_state([f"j{i}"]))
    assert 0 < len(cdr._STRING_BLOCKS) <= cdr.STRING_BLOCKS_KEPT
    huge = ["n" * 1000] * 8  # more than STRING_BLOCK_MAX bytes: built, never kept
    generated.encode_plain(joint_state(huge))
    assert tuple(huge) not in cdr._STRING_BLOCKS


TWELVE = [f"joint_{i}" for i in range(12)]


@pytest.mark.parametrize("plain", [False, True], ids=["typed", "plain"])
def test_a_decoded_list_of_names_is_the_callers(plain: bool) -> None:
    generated = Codec().of(JOINTS)  # its own decoders: nothing kept from other tests
    data = generated.encode_plain(joint_state(TWELVE))
    read = generated.read_plain if plain else generated.read
    for _ in range(2):  # read, then found
        first = read(data)
        names = first["name"] if plain else first.name
        names[0] = "changed"
        names.append("more")
    again = read(data)
    assert (again["name"] if plain else again.name) == TWELVE


def test_a_truncated_samples_names_are_not_kept() -> None:
    generated = Codec().of(JOINTS)
    data = generated.encode_plain(joint_state(TWELVE))
    cut = data[:data.index(b"joint_11") + 3]  # inside the last name
    with pytest.raises(CdrDecodeError, match="JointState"):
        generated.decode(cut)
    assert generated.decode(data).name == TWELVE
    assert generated.decode_plain(data)["name"] == TWELVE


def test_lists_of_the_same_count_and_of_others_read_as_they_are() -> None:
    generated = Codec().of(JOINTS)
    arm, gripper = ["shoulder", "elbow"], ["left", "right"]
    samples = [generated.encode_plain(joint_state(names))
               for names in (arm, gripper, ["solo"], arm, gripper, [], arm)]
    assert [generated.decode(data).name for data in samples] == [
        arm, gripper, ["solo"], arm, gripper, [], arm]


def test_the_blocks_a_decoder_keeps_are_bounded() -> None:
    generated = Codec().of(JOINTS)
    for count in range(3 * cdr_decode.STRING_BLOCKS_KEPT):
        names = [f"n{i}" for i in range(count)]
        assert generated.decode(generated.encode_plain(joint_state(names))).name == names
    kept = [value for name, value in generated.read.__globals__.items()
            if name.startswith("N") and isinstance(value, dict)]
    assert len(kept) == 1 and 0 < len(kept[0]) <= cdr_decode.STRING_BLOCKS_KEPT
    huge = ["n" * 1000] * 8  # more than STRING_BLOCK_MAX bytes: read, never kept
    assert generated.decode(generated.encode_plain(joint_state(huge))).name == huge
    assert all(len(block) <= cdr_decode.STRING_BLOCK_MAX for block, _, _ in kept[0].values())
