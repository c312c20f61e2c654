"""What a DDS participant names is shown, never obeyed: `topic list` printed topic and type
names as they came (Cyclone refuses such a topic name of its own, but not a type name, and a
remote participant of another vendor announces whatever it likes), so any participant on the
domain could send the operator's terminal escape sequences (retitle it, clear it, hide lines
of the listing). Red team 19 found it in `discover` (mDNS); the ROS listings had the same
fault."""


from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.topic import Topic
from waiting import eventually_sync

from tests.interop.test_cli import cli

HOSTILE = "\x1b]0;owned\x07\x1b[2J\u202e"


@dataclass
class String(IdlStruct, typename=f"std_msgs::msg::dds_::Str{HOSTILE}_"):
    data: str


@pytest.fixture
def hostile_topic(domain_id: int) -> Iterator[None]:
    participant = DomainParticipant(domain_id)
    topic = Topic(participant, "rt/evil", String)
    writer = DataWriter(participant, topic)
    yield
    del writer, topic, participant


@pytest.mark.usefixtures("hostile_topic")
def test_topic_list_shows_a_hostile_topic_name_escaped(domain_id: int) -> None:
    def listed() -> str | None:
        out = cli(domain_id, "topic", "list", "-t").stdout
        return out if "/evil" in out else None

    shown = eventually_sync(listed, timeout=60)
    assert not [c for c in shown if not c.isprintable() and c != "\n"], repr(shown)
    assert "/evil [std_msgs/msg/Str\\x1b]0;owned\\x07\\x1b[2J\\u202e]" in shown, shown
