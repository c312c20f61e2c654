"""`rcan-rtps bag record|play|info|reindex`: MCAP bags shaped like `ros2 bag`'s (see ros/bag.py)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import re
import sys
import time
from collections.abc import Iterable, Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

from .. import _stop_signals as stop_signals
from ..ros import qos as qos_mod
from ..ros.bag import (
    BagDamage,
    BagError,
    BagMessage,
    BagReader,
    BagSummary,
    BagTopic,
    BagWriter,
    ReindexedFile,
    qos_dict,
    reindex,
)
from ..ros.errors import CdrDecodeError, SampleTooLarge
from ..ros.graph import Direction, Endpoint, RosGraph
from ..ros.names import is_hidden, mangle_topic
from ..ros.participant import RosNode, RosPublisher, RosSubscription
from ._common import make_node
from ._echo import adapted_qos
from ._governed import UNGOVERNED, GovernorGuard

DISCOVERY_PERIOD = 0.1  # s between looks for new topics while recording
RECORD_DEPTH = 1000  # reader history: a slow disk must not cost messages
MATCH_PATIENCE = 3.0  # s `play` waits for known subscriptions to match its publishers
# Our writer matching a reader does not mean the reader has matched our writer yet (each side
# learns of the other on its own), and a Fast DDS reader drops data from writers it does not
# know: so a little more time before the first message.
MATCH_GRACE = 0.5
LABEL_WIDTH = 19  # ros2 bag info's label column


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("bag", help="record, play and inspect MCAP bags")
    actions = parser.add_subparsers(dest="bag_command", required=True)

    record = actions.add_parser("record", help="record topics into an MCAP bag")
    record.add_argument("topics", metavar="TOPIC", nargs="*", help="topics to record")
    record.add_argument("--topics", dest="more_topics", nargs="+", default=[], metavar="TOPIC",
                        help="more topics to record (as the positional TOPIC arguments)")
    record.add_argument("-a", "--all", "--all-topics", dest="all", action="store_true",
                        help="record every topic (new ones too)")
    record.add_argument("-e", "--regex", default="", help="record topics matching this regex")
    record.add_argument("-x", "--exclude-regex", default="",
                        help="leave out topics matching this regex")
    record.add_argument("--include-hidden-topics", action="store_true",
                        help="with --all/--regex: also topics whose name has a part starting "
                        "with `_`")
    record.add_argument("-o", "--output", default="",
                        help="bag folder (default: rosbag2_<date>-<time>)")
    record.add_argument("-s", "--storage", default="mcap", choices=("mcap",),
                        help="storage format (MCAP, the ROS 2 default since Iron)")
    record.add_argument("--duration", type=float, default=0.0,
                        help="stop after S seconds (default: until Ctrl-C, SIGTERM or "
                        "SIGHUP)")
    record.set_defaults(func=lambda a: stop_signals.run(_record(a)))

    play = actions.add_parser("play", help="republish a bag with its original timing")
    play.add_argument("bag", metavar="BAG", help="bag folder or .mcap file")
    play.add_argument("-r", "--rate", type=float, default=1.0, help="speed factor (default 1)")
    play.add_argument("-l", "--loop", action="store_true", help="play again from the start, "
                      "until Ctrl-C")
    play.add_argument("--topics", nargs="+", default=[], metavar="TOPIC",
                      help="play only these topics")
    play.add_argument("-d", "--delay", type=float, default=0.0,
                      help="seconds to wait before playing")
    play.add_argument("--start-offset", type=float, default=0.0,
                      help="skip the first S seconds of the bag")
    play.add_argument("--playback-duration", type=float, default=-1.0,
                      help="play at most S seconds of the bag (default: all)")
    play.add_argument("-m", "--remap", nargs="+", default=[], metavar="FROM:=TO",
                      help="publish topic FROM under the name TO")
    play.add_argument(UNGOVERNED[0], action="store_true", help=UNGOVERNED[1])
    play.set_defaults(func=lambda a: stop_signals.run(_play(a)))

    info = actions.add_parser(
        "info", help="summary of a bag",
        description="The bag's summary (read from each file's MCAP summary section), and the "
        "damage its data section shows: chunks whose CRC does not match or that do not "
        "inflate, and definitions the summary contradicts. Reading the data section reads "
        f"every chunk: done by default for bags up to {CHECK_AUTO_BYTES >> 20} MiB.")
    info.add_argument("bag", metavar="BAG", help="bag folder or .mcap file")
    info.add_argument("--check", action=argparse.BooleanOptionalAction, default=None,
                      help="read every chunk for damage (default: only for bags up to "
                      f"{CHECK_AUTO_BYTES >> 20} MiB; larger ones say they were not read)")
    info.set_defaults(func=info_command)

    rebuild = actions.add_parser(
        "reindex", help="rebuild a bag a recorder left unfinished (killed, crashed): its "
        "MCAP summary and indexes, and metadata.yaml")
    rebuild.add_argument("bag", metavar="BAG", help="bag folder")
    rebuild.set_defaults(func=reindex_command)


# -- record -----------------------------------------------------------------------
def _default_output() -> str:
    return datetime.now().strftime("rosbag2_%Y_%m_%d-%H_%M_%S")


class _Selection:
    """Which topics a `record` wants: named ones, all, or by regex, minus the excluded."""

    def __init__(self, node: RosNode, args: argparse.Namespace) -> None:
        self.named = {node.resolve(t) for t in [*args.topics, *args.more_topics]}
        self.all = args.all
        self.regex = re.compile(args.regex) if args.regex else None
        self.exclude = re.compile(args.exclude_regex) if args.exclude_regex else None
        self.hidden = args.include_hidden_topics
        if not (self.named or self.all or self.regex):
            raise ValueError("name topics to record, or pass --all or --regex")

    def wants(self, topic: str) -> bool:
        if topic in self.named:
            return True
        if self.exclude and self.exclude.search(topic):
            return False
        if not self.hidden and is_hidden(topic):
            return False
        return self.all or bool(self.regex and self.regex.search(topic))


class _Recorder:
    def __init__(self, node: RosNode, writer: BagWriter) -> None:
        self.node, self.writer = node, writer
        self.subscriptions: dict[str, RosSubscription] = {}

    def follow(self, topic: str, publishers: list[Endpoint]) -> None:
        types = sorted({p.ros_type for p in publishers})
        if topic in self.subscriptions or not types:
            return
        if len(types) > 1:
            print(f"warning: '{topic}' has several types ({', '.join(types)}); not recorded",
                  file=sys.stderr)
            self.subscriptions[topic] = None  # type: ignore[assignment]  # asked once
            return
        type_name = types[0]
        self.node.store.message(type_name)  # an unknown type fails here, not on the wire
        offered = [qos_dict(p.qos, history_known=False) for p in publishers]
        self.writer.add_topic(topic, type_name, offered)
        qos = adapted_qos(publishers).with_(depth=RECORD_DEPTH)

        def on_message(data: Any, topic: str = topic) -> None:  # the bytes as they came
            self.writer.write(topic, time.time_ns(), bytes(data))

        self.subscriptions[topic] = self.node.create_subscription(
            topic, type_name, qos, callback=on_message, raw=True)
        print(f"Subscribed to topic '{topic}'", flush=True)

    def close(self) -> None:
        for sub in self.subscriptions.values():
            if sub is not None:
                sub.close()


async def _record(args: argparse.Namespace) -> int:
    output = Path(args.output or _default_output())
    with make_node(args) as node:
        selection = _Selection(node, args)
        stop = asyncio.Event()
        # From before the bag exists: Ctrl-C, SIGTERM or SIGHUP (its terminal or ssh session
        # closed) end the recording with the bag closed, complete, exit 0; killed, it would
        # be left to `bag reindex`.
        with stop_signals.taking_over(lambda sig: stop.set()):
            writer = await _recorded(node, selection, output, stop, args.duration)
        print(f"Recorded {writer.message_count} messages to '{output}'", flush=True)
    return 0


async def _recorded(node: RosNode, selection: _Selection, output: Path, stop: asyncio.Event,
                    duration: float) -> BagWriter:
    """The bag, written until `stop` or `duration` s (0: no limit), then closed."""
    writer = BagWriter(output, node.store)
    recorder = _Recorder(node, writer)
    graph = RosGraph(node)
    deadline = time.monotonic() + duration if duration > 0 else None
    print(f"Recording to '{output}'...", flush=True)
    try:
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline) \
                and writer.failure is None:  # a full disk ends the recording
            graph.refresh()
            for topic, pubs in _publishers_by_topic(graph).items():
                if selection.wants(topic):
                    recorder.follow(topic, pubs)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), DISCOVERY_PERIOD)
    finally:
        recorder.close()
        writer.close()
    return writer


def _publishers_by_topic(graph: RosGraph) -> dict[str, list[Endpoint]]:
    found: dict[str, list[Endpoint]] = {}
    for e in graph.endpoints():
        if e.direction is Direction.PUBLISHER and e.dds_topic.startswith("rt/"):
            found.setdefault(e.ros_name, []).append(e)
    return found


# -- play -------------------------------------------------------------------------
def play_qos(topic: BagTopic) -> qos_mod.QosProfile:
    """The recorded publishers' QoS when they agree; else as strict as all of them allow."""
    offered = topic.offered_qos
    if not offered:
        return qos_mod.DEFAULT
    if all(p == offered[0] for p in offered):
        return offered[0]
    profile = qos_mod.DEFAULT
    if any(p.reliability is qos_mod.Reliability.BEST_EFFORT for p in offered):
        profile = profile.with_(reliability=qos_mod.Reliability.BEST_EFFORT)
    if all(p.durability is qos_mod.Durability.TRANSIENT_LOCAL for p in offered):
        profile = profile.with_(durability=qos_mod.Durability.TRANSIENT_LOCAL)
    return profile


def _remaps(pairs: list[str]) -> dict[str, str]:
    remaps = {}
    for pair in pairs:
        source, sep, target = pair.partition(":=")
        if not sep or not source or not target:
            raise ValueError(f"bad remap {pair!r}: expected FROM:=TO")
        remaps[source] = target
    return remaps


def _publishers(node: RosNode, topics: list[BagTopic],
                remaps: dict[str, str]) -> dict[str, RosPublisher]:
    publishers = {}
    for topic in topics:
        if topic.serialization_format != "cdr":  # its bytes would go out as CDR
            print(f"warning: '{topic.name}' is encoded {topic.serialization_format[:32]!r}, "
                  "not cdr; not played", file=sys.stderr)
            continue
        if topic.type not in node.store:
            print(f"warning: type {topic.type} of '{topic.name}' is unknown (add its IDL with "
                  "--idl-path); not played", file=sys.stderr)
            continue
        publishers[topic.name] = node.create_publisher(
            remaps.get(topic.name, topic.name), topic.type, play_qos(topic))
    return publishers


async def _await_matches(node: RosNode, publishers: dict[str, RosPublisher]) -> None:
    """Lets the subscriptions already on the graph match first, so none misses the start.
    Its graph is closed after the one look: left open, the node's reader thread kept taking
    ros_discovery_info into it (and kept its reader) for as long as the playback ran."""
    graph = RosGraph(node)
    try:
        await graph.settle(0.5, patience=1.0)
        wanted_by = {pub.topic: sum(1 for e in graph.topic_endpoints(pub.topic)
                                    if e.direction is Direction.SUBSCRIPTION)
                     for pub in publishers.values()}
    finally:
        graph.close()
    deadline = time.monotonic() + MATCH_PATIENCE
    matched = False
    for pub in publishers.values():
        wanted = wanted_by[pub.topic]
        left = deadline - time.monotonic()
        if wanted and left > 0:
            matched = True
            with contextlib.suppress(Exception):
                await pub.wait_for_subscribers(wanted, timeout=left)
    if matched:
        await asyncio.sleep(MATCH_GRACE)


async def _play(args: argparse.Namespace) -> int:
    if args.rate <= 0:
        raise ValueError("--rate must be positive")
    reader = BagReader(Path(args.bag))
    summary = reader.summary()
    wanted = set(args.topics)
    topics = [t for t in summary.topics if not wanted or t.name in wanted]
    with make_node(args) as node:
        publishers = _publishers(node, topics, _remaps(args.remap))
        await _await_matches(node, publishers)
        governor = GovernorGuard(RosGraph(node), {mangle_topic(p.topic): p.topic
                                                  for p in publishers.values()},
                                 allowed=args.ungoverned)
        await governor.look_before_sending()
        if args.delay > 0:
            await asyncio.sleep(args.delay)
        refused = _Refused()
        while True:
            await _play_once(reader, summary, publishers, args, refused, governor)
            if not args.loop:
                break
        await asyncio.sleep(0.3)  # let reliable delivery finish before the participant goes
    refused.check(args.bag)
    return 0


def playback(messages: Iterable[BagMessage], begin_ns: int, end_ns: int | None,
             rate: float) -> Iterator[tuple[float, BagMessage]]:
    """(seconds after the start of playback, message) for each message in the window: the
    recorded gaps, divided by `rate`."""
    for message in messages:
        if message.log_time_ns < begin_ns:
            continue
        if end_ns is not None and message.log_time_ns > end_ns:
            break
        yield (message.log_time_ns - begin_ns) / 1e9 / rate, message


class _Refused:
    """The bag's messages DDS refused to publish (not the CDR of their topic's type): played
    past, then told in one line when the playback ends."""

    def __init__(self) -> None:
        self.count = 0
        self.first = ""

    def add(self, message: BagMessage, error: CdrDecodeError | SampleTooLarge) -> None:
        if not self.count:
            self.first = f"'{message.topic}' at {format_seconds(message.log_time_ns)}: {error}"
        self.count += 1

    def check(self, bag: str) -> None:
        if self.count:
            raise BagError(f"{self.count} message(s) of '{bag}' were not published, DDS "
                           f"refused them (first: {self.first}); the others were played")


async def _play_once(reader: BagReader, summary: BagSummary,
                     publishers: dict[str, RosPublisher], args: argparse.Namespace,
                     refused: _Refused, governor: GovernorGuard) -> None:
    begin_ns = summary.start_ns + round(args.start_offset * 1e9)
    end_ns = begin_ns + round(args.playback_duration * 1e9) \
        if args.playback_duration >= 0 else None
    start = time.monotonic()
    for offset, message in playback(reader.messages(set(publishers)), begin_ns, end_ns,
                                    args.rate):
        # Awaited even when late (0 s): a stop signal lands here, between two messages, also
        # when the bag is played faster than it can be.
        await asyncio.sleep(max(0.0, start + offset - time.monotonic()))
        governor.check_when_due()  # a governor found since ends the playback
        pub = publishers[message.topic]
        try:
            pub.publish_cdr(message.data)
        except (CdrDecodeError, SampleTooLarge) as exc:  # a damaged, hostile or huge message
            refused.add(message, exc)


# -- info -------------------------------------------------------------------------
def format_size(size: int) -> str:
    value, unit = float(size), 0
    units = ("B", "KiB", "MiB", "GiB", "TiB")
    while value >= 1024 and unit < len(units) - 1:
        value /= 1024
        unit += 1
    return f"{value:.0f} {units[unit]}" if unit == 0 else f"{value:.1f} {units[unit]}"


def format_seconds(ns: int) -> str:
    return f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def format_time_point(ns: int) -> str:
    local = datetime.fromtimestamp(ns // 1_000_000_000)
    return (f"{local.strftime('%b %e %Y %H:%M:%S')}.{ns % 1_000_000_000:09d} "
            f"({format_seconds(ns)})")


def _labelled(label: str, lines: list[str]) -> list[str]:
    head = label.ljust(LABEL_WIDTH)
    if not lines:
        return [head]
    return [head + lines[0], *(" " * LABEL_WIDTH + line for line in lines[1:])]


def describe(summary: BagSummary, damage: BagDamage | None = None) -> str:
    topics = [f"Topic: {t.name} | Type: {t.type} | Count: {t.count} | "
              f"Serialization Format: {t.serialization_format}" for t in summary.topics]
    lines = [
        "",
        *_labelled("Files:", [f.name for f in summary.files]),
        *_labelled("Bag size:", [format_size(summary.size)]),
        *_labelled("Storage id:", ["mcap"]),
        *_labelled("ROS Distro:", [summary.ros_distro]),
        *_labelled("Duration:", [format_seconds(summary.end_ns - summary.start_ns) + "s"]),
        *_labelled("Start:", [format_time_point(summary.start_ns)]),
        *_labelled("End:", [format_time_point(summary.end_ns)]),
        *_labelled("Messages:", [str(summary.message_count)]),
        *_labelled("Topic information:", topics),
        *_labelled("Service:", ["0"]),
        "Service information: ",
        *_damage_lines(damage or BagDamage()),
    ]
    return "\n".join(lines)


def _damage_lines(damage: BagDamage) -> list[str]:
    """What the data section showed that the summary does not: none for a sound bag."""
    lines = []
    if damage.chunks:
        lines += _labelled("Damaged chunks:", [f"{len(damage.chunks)}", *damage.chunks])
    if damage.conflicts:
        lines += _labelled("Conflicts:", damage.conflicts)
    return lines


# `bag info` reads a bag's every chunk for damage up to this size unless told; a larger bag's
# summary comes at once, as `ros2 bag info`'s does (reading gigabytes takes minutes).
CHECK_AUTO_BYTES = 512 << 20


def info_command(args: argparse.Namespace) -> int:
    reader = BagReader(Path(args.bag))
    summary = reader.summary()
    check = args.check if args.check is not None else summary.size <= CHECK_AUTO_BYTES
    text = describe(summary, reader.damage() if check else None)
    if not check and args.check is None:
        text += ("\nChunks not read for damage: the bag is over "
                 f"{CHECK_AUTO_BYTES >> 20} MiB (--check reads them)")
    print(text)
    return 0


# -- reindex ----------------------------------------------------------------------
def _left_out(done: ReindexedFile) -> str:
    """What a damaged file's rebuild could not carry over, as the end of its line."""
    notes = []
    for start, end in done.skipped:
        notes.append(f"stepped over {end - start} B of damage at byte {start}, kept what "
                     "follows")
    if done.unreadable:
        notes.append(f"left out {done.unreadable} damaged record(s) or chunk(s) whose "
                     f"messages could not be read (first: {done.unreadable_why})")
    if done.dropped_bytes:
        notes.append(f"left out a torn last record of {done.dropped_bytes} B")
    if done.unattributed:
        notes.append(f"left out {done.unattributed} messages of a channel the file never "
                     "defines")
    for conflict in done.conflicts:
        notes.append(f"{conflict}: the first definition kept")
    if done.conflicted:
        notes.append(f"left out {done.conflicted} messages of a channel after its id was "
                     "defined again (of which definition, none can tell)")
    return f" ({'; '.join(notes)})" if notes else ""


def reindex_command(args: argparse.Namespace) -> int:
    for done in reindex(Path(args.bag), args.distro or ""):
        print(f"Reindexed '{done.path}': {done.messages} messages{_left_out(done)}")
    print(f"Wrote '{Path(args.bag) / 'metadata.yaml'}'")
    return 0
