"""ros/raw_cdr.py: cyclonedds' private raw write/take, pinned on the binding we ship with, and
the public-API fallback taken when they are missing or a writer wants XCDR2.

Each case writes with one path and reads with the other, so both directions are checked
against cyclonedds' own codec (its typed DataReader/DataWriter)."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator

import pytest
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from waiting import eventually

from rcan_rtps.ros import qos, raw_cdr
from rcan_rtps.ros.names import mangle_topic
from rcan_rtps.ros.participant import CdrSample, RosNode

SCAN = "sensor_msgs/msg/LaserScan"
VALUES = {"header": {"frame_id": "laser"}, "angle_max": 3.0, "ranges": [0.5, 1.5, 2.5],
          "intensities": [7.0]}


@pytest.fixture
async def node(domain_id: int) -> AsyncIterator[RosNode]:
    with RosNode("raw_cdr", "/raw", domain_id=domain_id, localhost=True) as made:
        yield made


@pytest.fixture(params=["private", "fallback"])
def path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    if request.param == "fallback":
        monkeypatch.setattr(raw_cdr, "_write", None)
        monkeypatch.setattr(raw_cdr, "_take", None)
    yield request.param


def test_the_private_calls_exist_in_the_pinned_binding() -> None:
    assert raw_cdr.AVAILABLE, "cyclonedds._clayer lost ddspy_write/ddspy_take: see raw_cdr.py"


async def test_raw_writes_reach_a_typed_cyclonedds_reader(node: RosNode, path: str) -> None:
    topic = node.topic(mangle_topic("/raw/scan"), SCAN)
    reader: DataReader[object] = DataReader(node.subscriber, topic)
    pub = node.create_publisher("/raw/scan", SCAN)
    await eventually(lambda: pub.matched_count() == 1)
    pub.publish(VALUES)
    samples = await _take(reader)
    expected = node.values.build(SCAN, VALUES)
    assert samples == [expected]  # decoded by cyclonedds itself


async def test_a_typed_cyclonedds_write_is_taken_as_its_bytes(node: RosNode, path: str) -> None:
    writer: DataWriter[object] = DataWriter(
        node.publisher, node.topic(mangle_topic("/raw/scan"), SCAN))
    sub = node.create_subscription("/raw/scan", SCAN, raw=True)
    typed = node.create_subscription("/raw/scan", SCAN)
    await eventually(lambda: sub.matched_count() == 1 and typed.matched_count() == 1)
    message = node.values.build(SCAN, VALUES)
    writer.write(message)
    data = await sub.get(timeout=10)
    assert isinstance(data, CdrSample) and data.sample_info.valid_data
    body = bytes(message.serialize())
    assert data[: len(body)] == body and not any(data[len(body):])  # at most zero padding
    decoded = await typed.get(timeout=10)
    assert node.values.to_plain(SCAN, decoded) == node.values.to_plain(SCAN, message)


def test_a_writer_that_wants_xcdr2_takes_the_public_path(node: RosNode) -> None:
    writer = node.create_writer(mangle_topic("/raw/scan"), SCAN, qos.DEFAULT)
    writer._use_version_2 = True  # what the binding sets for a DataRepresentation(XCDR2) QoS
    written: list[object] = []
    writer.write = written.append  # type: ignore[method-assign]
    raw_cdr.write(writer, node.codecs.of(SCAN).encode_plain(VALUES))
    assert written == [node.values.build(SCAN, VALUES)]


async def _take(reader: DataReader[object]) -> list[object]:
    for _ in range(200):
        samples = reader.take()
        if samples:
            return list(samples)
        await asyncio.sleep(0.05)
    raise AssertionError("nothing arrived")
