"""Reading a matched endpoint's QoS leaks nothing (`rcan_rtps.ros._cyclone_qos`).

The cyclonedds binding never freed the USER_DATA, TOPIC_DATA, GROUP_DATA and PARTITION that
Cyclone copies out for it: each read of a matched endpoint's data leaked them. A writer
announcing 16 kB of them, read 2,000 times, leaked ~32 MB; the process's anonymous memory
must now stay within a few MB over the reads. Memory is read, not time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cyclonedds.core import Policy
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import int32
from cyclonedds.pub import DataWriter, Publisher
from cyclonedds.qos import Qos
from cyclonedds.sub import DataReader, Subscriber
from cyclonedds.topic import Topic
from waiting import eventually_sync

import rcan_rtps.ros.qos  # noqa: F401  (what every DDS user of ours imports: the fix)


@dataclass
class Plain(IdlStruct, typename="leak_probe::Plain"):
    value: int32

READS = 2000
USER_DATA = b"typehash=RIHS01_" + b"a" * 4000 + b";"
TOPIC_DATA = b"t" * 4000
GROUP_DATA = b"g" * 4000
PARTITIONS = ["p" * 2000, "q" * 2000]


def _anonymous_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssAnon:"):
            return int(line.split()[1])
    raise AssertionError("no RssAnon in /proc/self/status")


def test_reading_a_matched_writer_s_qos_leaks_nothing(domain_id: int) -> None:
    participant = DomainParticipant(domain_id)
    topic = Topic(participant, "leak_probe", Plain,
                  qos=Qos(Policy.Topicdata(data=TOPIC_DATA)))
    publisher = Publisher(participant, qos=Qos(Policy.Groupdata(data=GROUP_DATA),
                                               Policy.Partition(partitions=PARTITIONS)))
    subscriber = Subscriber(participant, qos=Qos(Policy.Partition(partitions=PARTITIONS)))
    writer = DataWriter(publisher, topic, qos=Qos(Policy.Userdata(data=USER_DATA)))
    reader = DataReader(subscriber, topic)
    (handle,) = eventually_sync(lambda: reader.get_matched_publications(), timeout=20,
                                what="the writer matched")
    data = reader.get_matched_publication_data(handle)
    assert data.qos[Policy.Userdata].data == USER_DATA
    assert data.qos[Policy.Topicdata].data == TOPIC_DATA
    assert data.qos[Policy.Groupdata].data == GROUP_DATA
    assert list(data.qos[Policy.Partition].partitions) == PARTITIONS
    for _ in range(100):  # the allocator's own pools settle first
        reader.get_matched_publication_data(handle)
    before = _anonymous_kb()
    for _ in range(READS):
        reader.get_matched_publication_data(handle)
    grown_kb = _anonymous_kb() - before
    leaked_each = len(USER_DATA) + len(TOPIC_DATA) + len(GROUP_DATA) + sum(map(len, PARTITIONS))
    print(f"{READS} reads: +{grown_kb} kB (leaking, ~{READS * leaked_each >> 10} kB)")
    assert grown_kb < READS * leaked_each / 1024 / 8, grown_kb
    del writer
