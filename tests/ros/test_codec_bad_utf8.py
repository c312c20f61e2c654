"""A string whose bytes are not UTF-8 is read as rclpy reads it (U+FFFD for each bad
sequence), at any depth of a message, and the sample is not lost: the strict decoder hands
it to its lenient twin, from wherever the decode started (bytes, a memoryview, an offset)."""

from __future__ import annotations

from typing import Any

import pytest

from rcan_rtps.ros.serialization import Codec

pytestmark = pytest.mark.offline

CODEC = Codec()
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
VALUES = {"header": {"frame_id": "base"},
          "status": [{"level": 2, "name": "motor", "message": "hot",
                      "hardware_id": "m1", "values": [{"key": "temp", "value": "91"}]}]}


def spoiled(data: bytes, word: bytes) -> bytes:
    at = data.index(word)
    return data[:at + 1] + b"\xff" + data[at + 2:]  # same length: framing unchanged


def read_both(data: Any) -> tuple[dict[str, Any], Any]:
    codec = CODEC.of(DIAGNOSTICS)
    return codec.decode_plain(data), codec.decode(data)


@pytest.mark.parametrize("word", [b"base", b"motor", b"temp", b"91"])
@pytest.mark.parametrize("form", ["bytes", "memoryview", "bytearray"])
def test_bad_bytes_read_as_replacement_characters(word: bytes, form: str) -> None:
    good = CODEC.of(DIAGNOSTICS).encode_plain(VALUES)
    bad = spoiled(good, word)
    data: Any = {"bytes": bad, "memoryview": memoryview(bad), "bytearray": bytearray(bad)}[form]
    plain, typed = read_both(data)
    expected = word.decode()[0] + "\ufffd" + word.decode()[2:]
    texts = [plain["header"]["frame_id"], plain["status"][0]["name"],
             plain["status"][0]["values"][0]["key"], plain["status"][0]["values"][0]["value"]]
    assert expected in texts
    assert typed.status[0].values[0].key == plain["status"][0]["values"][0]["key"]
    assert typed.header.frame_id == plain["header"]["frame_id"]


def test_a_good_sample_after_a_bad_one_reads_strictly() -> None:
    good = CODEC.of(DIAGNOSTICS).encode_plain(VALUES)
    read_both(spoiled(good, b"motor"))
    plain, _ = read_both(good)
    assert plain["status"][0]["name"] == "motor"


def test_an_offset_start_is_kept_for_the_lenient_read() -> None:
    good = CODEC.of(DIAGNOSTICS).encode_plain(VALUES)
    bad = spoiled(good, b"base")
    padded = bad[:4] + b"\x00" * 8 + bad[4:]  # an in-band prefix: the body starts at 12
    message = CODEC.of(DIAGNOSTICS).decode(padded, offset=12)
    assert message.header.frame_id == "b\ufffdse"


def test_a_type_whose_only_strings_are_nested_reads_them_leniently() -> None:
    """rmw's ros_discovery_info: its strings are in the elements of a sequence only (the
    nested functions are written after the entry point's)."""
    codec = CODEC.of("rmw_dds_common/msg/ParticipantEntitiesInfo")
    good = codec.encode_plain({"node_entities_info_seq": [
        {"node_namespace": "/", "node_name": "evil_node"}]})
    bad = spoiled(good, b"_node")
    assert codec.decode(bad).node_entities_info_seq[0].node_name == "evil_\ufffdode"
    assert codec.decode_plain(bad)["node_entities_info_seq"][0]["node_name"] == "evil_\ufffdode"
