"""A DDS peer that floods discovery: a participant makes `per_round` writers and leaves (its
writers with it), and again, as fast as it can, for `rounds` rounds or until its stdin closes;
two threads do it at once, so that one's participant is being made (no discovery for a
moment) while the other's writers come and go. Each writer is an endpoint that appears and
leaves in every other participant's builtin publication reader. Plain cyclonedds in a process
of its own (another machine's peer, as far as the victim's CPU goes): `python
discovery_flood.py DOMAIN ROUNDS PER_ROUND`. Prints `flooding` once writers exist, then `done
N` (the rounds made).
"""

from __future__ import annotations

import os
import sys
import threading
from dataclasses import dataclass

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import int32
from cyclonedds.pub import DataWriter, Publisher
from cyclonedds.topic import Topic

THREADS = 2


@dataclass
class Int32(IdlStruct, typename="std_msgs::msg::dds_::Int32_"):
    data: int32


def _rounds(domain_id: int, rounds: int, per_round: int, stop: threading.Event,
            first: threading.Event, done: list[int]) -> None:
    for _ in range(rounds):
        if stop.is_set():
            return
        participant = DomainParticipant(domain_id)
        publisher = Publisher(participant)
        topic = Topic(participant, f"rt/flood_{os.getpid()}", Int32)  # one topic: all discovery
        writers = [DataWriter(publisher, topic) for _ in range(per_round)]
        first.set()
        del writers, topic, publisher
        participant.__del__()  # its writers leave with it
        done.append(1)


def flood(domain_id: int, rounds: int, per_round: int) -> int:
    stop, first, done = threading.Event(), threading.Event(), []
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    threads = [threading.Thread(target=_rounds, args=(domain_id, rounds, per_round, stop,
                                                      first, done)) for _ in range(THREADS)]
    for thread in threads:
        thread.start()
    first.wait()
    print("flooding", flush=True)
    for thread in threads:
        thread.join()
    print(f"done {len(done)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(flood(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])))
