"""ROS 2 bags in MCAP, laid out like `ros2 bag` writes them.

A bag is a directory holding `<name>_0.mcap` and `metadata.yaml`. The MCAP file follows
the ROS 2 profile: header profile `ros2`; one schema per type, encoding `ros2msg`, whose data
is the concatenated `.msg` definition; one channel per topic, message encoding `cdr`,
with `offered_qos_profiles` (YAML) and `topic_type_hash` metadata; messages are the CDR
bytes as they travelled, encapsulation header included, stamped with the receive time.
A `rosbag2` metadata record repeats `metadata.yaml` as `ros2 bag` does. Readers accept such
a directory (any writer's: rosbag2, rosbags, …) or a bare `.mcap` file.

A recorder may die without closing its bag (SIGKILL, power, OOM). So the writer closes the
chunk in progress and rewrites `metadata.yaml` (atomically: a temporary file, then a rename)
every `FLUSH_PERIOD`: what a killed recorder leaves is a valid MCAP data section without its
summary, which a sequential reader reads up to the last flush, and `reindex` turns into a
complete bag (summary, indexes, metadata) like `ros2 bag reindex`.
"""

from __future__ import annotations

import io
import os
import struct
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from .. import __version__
from .errors import WireError
from .qos import Durability, History, QosProfile, Reliability
from .typesys.msgdef import full_definition
from .typesys.store import TypeStore

METADATA_FILE = "metadata.yaml"
METADATA_VERSION = 9  # the rosbag2 metadata version of Jazzy
_INFINITE = {"sec": 9223372036, "nsec": 854775807}  # RMW_DURATION_INFINITE, as Jazzy writes it
_UNSPECIFIED = {"sec": 0, "nsec": 0}
FLUSH_PERIOD = 0.5  # s: the most a killed recorder loses (and the age of metadata.yaml)
MCAP_MAGIC = b"\x89MCAP0\r\n"
RECORD_HEAD = struct.Struct("<BQ")  # every MCAP record: opcode, then length
REINDEX_HINT = "`rcan-rtps bag reindex {bag}` rebuilds its summary and index"


class BagError(WireError):
    """A bag that cannot be written or read."""


# -- QoS as rosbag2 writes it ------------------------------------------------------
def _duration(seconds: float | None) -> dict[str, int]:
    if seconds is None:
        return dict(_INFINITE)
    ns = round(seconds * 1e9)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def qos_dict(profile: QosProfile, *, history_known: bool = True) -> dict[str, Any]:
    # Discovery does not carry a writer's history, so rmw reports it as unknown, depth 0.
    history = profile.history.value if history_known else "unknown"
    return {
        "history": history,
        "depth": profile.depth if history_known else 0,
        "reliability": profile.reliability.value,
        "durability": profile.durability.value,
        "deadline": _duration(profile.deadline_s),
        "lifespan": _duration(profile.lifespan_s),
        "liveliness": "automatic",
        "liveliness_lease_duration": dict(_INFINITE),
        "avoid_ros_namespace_conventions": False,
    }


def _seconds(value: Any) -> float | None:
    if not isinstance(value, dict):
        return None
    sec, nsec = int(value.get("sec", 0)), int(value.get("nsec", 0))
    if (sec, nsec) in ((_INFINITE["sec"], _INFINITE["nsec"]), (0, 0), (2147483647, 4294967295)):
        return None
    return sec + nsec / 1e9


def parse_offered_qos(text: str | list[Any] | None) -> list[QosProfile]:
    """The profiles of a channel's `offered_qos_profiles` (YAML text or a parsed list)."""
    items = yaml.safe_load(text) if isinstance(text, str) else text
    profiles = []
    for item in items or []:
        history = str(item.get("history", "keep_last")).lower()
        depth = int(item.get("depth", 0) or 0)
        profiles.append(QosProfile(
            history=History.KEEP_ALL if history == "keep_all" else History.KEEP_LAST,
            depth=depth if depth > 0 else 10,
            reliability=Reliability.BEST_EFFORT
            if str(item.get("reliability")).lower() == "best_effort" else Reliability.RELIABLE,
            durability=Durability.TRANSIENT_LOCAL
            if str(item.get("durability")).lower() == "transient_local" else Durability.VOLATILE,
            lifespan_s=_seconds(item.get("lifespan")),
            deadline_s=_seconds(item.get("deadline")),
        ))
    return profiles


# -- writing ------------------------------------------------------------------------
@dataclass
class _TopicRecord:
    name: str
    type: str
    type_hash: str
    offered: list[dict[str, Any]]
    channel_id: int
    count: int = 0


class BagWriter:
    """Writes one bag; `write` may be called from any thread. Every `flush_period` seconds
    (a thread of its own) what was written so far reaches the file and `metadata.yaml`."""

    def __init__(self, directory: Path, store: TypeStore, *,
                 flush_period: float = FLUSH_PERIOD) -> None:
        if directory.exists():
            raise BagError(f"output folder '{directory}' already exists")
        directory.mkdir(parents=True)
        self.directory = directory
        self.file_name = f"{directory.name}_0.mcap"
        self.store = store
        self._stream = (directory / self.file_name).open("wb")
        self._mcap = Writer(self._stream, compression=CompressionType.NONE)
        self._mcap.start(profile="ros2", library=f"rcan-rtps {__version__}")
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _TopicRecord] = {}
        self._lock = threading.Lock()
        self._start_ns: int | None = None
        self._end_ns = 0
        self._closed = False
        self.flush()  # the header and metadata.yaml on disk from the start
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_every, args=(flush_period,),
                                         name=f"bag-flush-{directory.name}", daemon=True)
        self._flusher.start()

    def add_topic(self, name: str, type_name: str, offered: list[dict[str, Any]]) -> None:
        with self._lock:
            if name in self._topics:
                return
            schema_id = self._schemas.get(type_name)
            if schema_id is None:
                text = full_definition(type_name, self.store.message)
                schema_id = self._mcap.register_schema(type_name, "ros2msg", text.encode())
                self._schemas[type_name] = schema_id
            type_hash = self.store.hash_of(type_name) if self.store.distro != "humble" else ""
            metadata = {"offered_qos_profiles": _qos_text(offered)}
            if type_hash:
                metadata["topic_type_hash"] = type_hash
            channel_id = self._mcap.register_channel(name, "cdr", schema_id, metadata)
            self._topics[name] = _TopicRecord(name, type_name, type_hash, offered, channel_id)

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        with self._lock:
            if self._closed:
                return
            record = self._topics[topic]
            self._mcap.add_message(record.channel_id, log_time=log_time_ns, data=data,
                                   publish_time=log_time_ns, sequence=record.count)
            record.count += 1
            if self._start_ns is None:
                self._start_ns = log_time_ns
            self._start_ns = min(self._start_ns, log_time_ns)
            self._end_ns = max(self._end_ns, log_time_ns)

    @property
    def message_count(self) -> int:
        return sum(t.count for t in self._topics.values())

    def flush(self) -> None:
        """The chunk in progress to the file, then metadata.yaml counting what it holds
        (under the lock: a message counted there is in the file)."""
        with self._lock:
            if self._closed:
                return
            self._mcap.flush()
            write_metadata(self.directory, self._metadata())

    def _flush_every(self, period: float) -> None:
        while not self._stop.wait(period):
            try:
                self.flush()
            except OSError as exc:  # a full disk: say so once, keep recording in memory
                print(f"warning: bag '{self.directory}' could not be flushed: {exc}",
                      file=sys.stderr)
                return

    def close(self) -> None:
        self._stop.set()
        if self._flusher.is_alive() and self._flusher is not threading.current_thread():
            self._flusher.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            info = self._metadata()
            self._mcap.add_metadata("rosbag2", {
                "serialized_metadata": yaml.safe_dump(info, sort_keys=False),
                "ROS_DISTRO": self.store.distro,
            })
            self._mcap.finish()
            self._stream.close()
            write_metadata(self.directory, info)

    def _metadata(self) -> dict[str, Any]:
        files = [(self.file_name, self._start_ns or 0, self._end_ns, self.message_count)]
        return bag_metadata(list(self._topics.values()), files, self.store.distro)


def bag_metadata(topics: list[_TopicRecord], files: list[tuple[str, int, int, int]],
                 distro: str) -> dict[str, Any]:
    """`rosbag2_bagfile_information` of a bag: its topics, and its files as (name, first
    and last receive time, message count)."""
    counted = [f for f in files if f[3]]
    start = min((f[1] for f in counted), default=0)
    end = max((f[2] for f in counted), default=0)
    count = sum(f[3] for f in files)
    return {
        "version": METADATA_VERSION,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": max(0, end - start)},
        "starting_time": {"nanoseconds_since_epoch": start},
        "message_count": count,
        "topics_with_message_count": [{
            "topic_metadata": {
                "name": t.name, "type": t.type, "serialization_format": "cdr",
                "offered_qos_profiles": t.offered,
                "type_description_hash": t.type_hash,
            },
            "message_count": t.count,
        } for t in topics],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [name for name, *_ in files],
        "files": [{
            "path": name,
            "starting_time": {"nanoseconds_since_epoch": first if n else 0},
            "duration": {"nanoseconds": max(0, last - first) if n else 0},
            "message_count": n,
        } for name, first, last, n in files],
        "custom_data": None,
        "ros_distro": distro,
    }


def write_metadata(directory: Path, info: dict[str, Any]) -> None:
    """metadata.yaml, replaced in one step: a reader (or a crash) sees the old or the new."""
    text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)
    temporary = directory / f".{METADATA_FILE}.tmp"
    temporary.write_text(text, encoding="utf-8")
    os.replace(temporary, directory / METADATA_FILE)


def _qos_text(offered: list[dict[str, Any]]) -> str:
    return yaml.safe_dump(offered, sort_keys=False).rstrip() if offered else ""


# -- reading ------------------------------------------------------------------------
@dataclass
class BagTopic:
    name: str
    type: str
    count: int
    serialization_format: str
    offered_qos: list[QosProfile] = field(default_factory=list)
    type_hash: str = ""
    schema_text: str = ""


@dataclass
class BagSummary:
    files: list[Path]
    size: int
    start_ns: int
    end_ns: int
    message_count: int
    topics: list[BagTopic]
    ros_distro: str


@dataclass(frozen=True)
class BagMessage:
    topic: str
    type: str
    log_time_ns: int
    data: bytes


def bag_files(path: Path) -> list[Path]:
    """The MCAP files of a bag directory (in metadata order) or the file itself."""
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise BagError(f"bag path '{path}' does not exist")
    meta = path / METADATA_FILE
    if meta.is_file():
        info = _load_metadata(meta)
        names = info.get("relative_file_paths") or []
        files = [path / Path(n).name for n in names]
        if files and all(f.is_file() for f in files):
            return files
    found = sorted(path.glob("*.mcap"))
    if not found:
        raise BagError(f"no storage could be initialized from '{path}': no .mcap file")
    return found


def _load_metadata(meta: Path) -> dict[str, Any]:
    try:
        loaded = yaml.safe_load(meta.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise BagError(f"'{meta}' is not a bag's metadata.yaml: {_first_line(exc)}") from None
    info = loaded.get("rosbag2_bagfile_information", {}) if isinstance(loaded, dict) else {}
    return info if isinstance(info, dict) else {}


def _distro_of(path: Path, records: dict[str, dict[str, str]]) -> str:
    meta = path / METADATA_FILE
    if path.is_dir() and meta.is_file():
        distro = _load_metadata(meta).get("ros_distro")
        if distro:
            return str(distro)
    return records.get("rosbag2", {}).get("ROS_DISTRO", "") or "unknown"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _bag_of(file: Path) -> Path:
    """What to name in the reindex hint: the bag folder a file is in, or the file."""
    return file.parent if (file.parent / METADATA_FILE).is_file() else file


def check_mcap(file: Path) -> None:
    """Fails with what is wrong when `file` cannot be an MCAP file at all."""
    with file.open("rb") as stream:
        head = stream.read(len(MCAP_MAGIC))
    if not head:
        raise BagError(f"'{file}' is empty (did the recorder die before writing anything?)")
    if head != MCAP_MAGIC[:len(head)] or len(head) < len(MCAP_MAGIC):
        raise BagError(f"'{file}' is not an MCAP file")


def _damaged(file: Path, exc: BaseException) -> BagError:
    return BagError(f"'{file}' is damaged or cut short ({_first_line(exc)}); "
                    + REINDEX_HINT.format(bag=_bag_of(file)))


# Reading a damaged file fails in the mcap library's parsing (struct, sizes, decoding).
_PARSE_ERRORS = (McapError, struct.error, ValueError, IndexError, KeyError, EOFError)


class BagReader:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.files = bag_files(path)

    def summary(self) -> BagSummary:
        topics: dict[str, BagTopic] = {}
        start, end, count = 2**63, 0, 0
        records: dict[str, dict[str, str]] = {}
        for file in self.files:
            check_mcap(file)
            try:
                with file.open("rb") as stream:
                    reader = make_reader(stream)
                    summary = reader.get_summary()
                    if summary is None:
                        raise BagError(f"'{file}' has no summary section (was the recording "
                                       "cut short?); " + REINDEX_HINT.format(bag=_bag_of(file)))
                    for rec in reader.iter_metadata():
                        records[rec.name] = dict(rec.metadata)
            except _PARSE_ERRORS as exc:
                raise _damaged(file, exc) from None
            stats = summary.statistics
            if stats is not None and stats.message_count:
                start = min(start, stats.message_start_time)
                end = max(end, stats.message_end_time)
                count += stats.message_count
            for channel_id, channel in summary.channels.items():
                schema = summary.schemas.get(channel.schema_id)
                topic = topics.setdefault(channel.topic, BagTopic(
                    channel.topic, schema.name if schema else "", 0, channel.message_encoding,
                    parse_offered_qos(channel.metadata.get("offered_qos_profiles") or None),
                    channel.metadata.get("topic_type_hash", ""),
                    schema.data.decode("utf-8", "replace") if schema else ""))
                if stats is not None:
                    topic.count += stats.channel_message_counts.get(channel_id, 0)
        return BagSummary(self.files, sum(f.stat().st_size for f in self.files),
                          start if count else 0, end if count else 0, count,
                          sorted(topics.values(), key=lambda t: t.name),
                          _distro_of(self.path, records))

    def messages(self, topics: set[str] | None = None) -> Iterator[BagMessage]:
        """Every message in receive-time order (per file, files in order)."""
        for file in self.files:
            check_mcap(file)
            with file.open("rb") as stream:
                reader = make_reader(stream)
                found = reader.iter_messages(topics=sorted(topics) if topics else None,
                                             log_time_order=True)
                while True:
                    try:
                        schema, channel, message = next(found)
                    except StopIteration:
                        break
                    except _PARSE_ERRORS as exc:
                        raise _damaged(file, exc) from None
                    yield BagMessage(channel.topic, schema.name if schema else "",
                                     message.log_time, message.data)


# -- reindex ------------------------------------------------------------------------
@dataclass
class ReindexedFile:
    path: Path
    messages: int
    dropped_bytes: int  # the torn record(s) at the end, left out


def complete_records(file: Path) -> tuple[bytes, int]:
    """The file up to its last complete record (the whole file when it is complete), and
    how many bytes after that were left out. A killed writer's last write may be torn."""
    check_mcap(file)
    data = file.read_bytes()
    end = offset = len(MCAP_MAGIC)
    while offset + RECORD_HEAD.size <= len(data):
        _, length = RECORD_HEAD.unpack_from(data, offset)
        offset += RECORD_HEAD.size + length
        if offset > len(data):
            break
        end = offset
    if data[end:] == MCAP_MAGIC:  # a closed file ends with the magic after its footer
        end = len(data)
    return data[:end], len(data) - end


def _records(data: bytes, file: Path) -> Iterator[Any]:
    """The records of a prefix of complete records (chunks opened), up to the footer."""
    found = StreamReader(io.BytesIO(data)).records
    while True:
        try:
            yield next(found)
        except (StopIteration, McapError):  # McapError: EndOfFile where the prefix ends
            return
        except (struct.error, ValueError, IndexError) as exc:
            raise BagError(f"'{file}' is damaged inside its data ({_first_line(exc)}); "
                           "cannot reindex it") from None


def reindex_file(file: Path, distro: str) -> tuple[ReindexedFile, list[_TopicRecord],
                                                    tuple[int, int]]:
    """Rewrites `file` as a complete MCAP (summary, chunk and message indexes, statistics)
    holding every message its complete records hold; the original is replaced in one step."""
    data, dropped = complete_records(file)
    temporary = file.with_name(f".{file.name}.reindex")
    topics: dict[int, _TopicRecord] = {}
    schema_ids: dict[int, int] = {}
    schema_names: dict[int, str] = {}
    channels: dict[int, int] = {}
    first, last, count = 2**63, 0, 0
    profile, library = "ros2", f"rcan-rtps {__version__} (reindex)"
    with temporary.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.NONE)
        records = _records(data, file)
        header = next(records, None)
        if header is not None and hasattr(header, "profile"):
            profile = header.profile or profile
        writer.start(profile=profile, library=library)
        for record in records:
            if isinstance(record, Schema) and record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(record.name, record.encoding,
                                                               record.data)
                schema_names[record.id] = record.name
            elif isinstance(record, Channel) and record.id not in channels:
                channels[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0),
                    dict(record.metadata))
                topics[record.id] = _TopicRecord(
                    record.topic, schema_names.get(record.schema_id, ""),
                    record.metadata.get("topic_type_hash", ""),
                    _offered_list(record.metadata.get("offered_qos_profiles", "")),
                    channels[record.id])
            elif isinstance(record, Message) and record.channel_id in channels:
                writer.add_message(channels[record.channel_id], log_time=record.log_time,
                                   data=record.data, publish_time=record.publish_time,
                                   sequence=record.sequence)
                topics[record.channel_id].count += 1
                first, last = min(first, record.log_time), max(last, record.log_time)
                count += 1
            elif isinstance(record, Metadata) and record.name != "rosbag2":
                writer.add_metadata(record.name, dict(record.metadata))
        info = bag_metadata(list(topics.values()),
                            [(file.name, first, last, count)], distro)
        writer.add_metadata("rosbag2", {
            "serialized_metadata": yaml.safe_dump(info, sort_keys=False), "ROS_DISTRO": distro})
        writer.finish()
    os.replace(temporary, file)
    return ReindexedFile(file, count, dropped), list(topics.values()), (first, last)


def _offered_list(text: str) -> list[dict[str, Any]]:
    try:
        loaded = yaml.safe_load(text) if text else []
    except yaml.YAMLError:
        return []
    return [item for item in loaded if isinstance(item, dict)] if isinstance(loaded, list) \
        else []


def reindex(path: Path, distro: str = "") -> list[ReindexedFile]:
    """Like `ros2 bag reindex`: every MCAP file of the bag folder `path` rebuilt complete,
    and its metadata.yaml written anew from what the files hold."""
    if not path.is_dir():
        raise BagError(f"'{path}' is not a bag folder (reindex rebuilds a folder's files and "
                       "its metadata.yaml)")
    files = sorted(path.glob("*.mcap"))
    if not files:
        raise BagError(f"no .mcap file in '{path}'")
    meta = path / METADATA_FILE
    old = _load_metadata(meta) if meta.is_file() else {}
    distro = distro or str(old.get("ros_distro") or "") or "unknown"
    done: list[ReindexedFile] = []
    merged: dict[str, _TopicRecord] = {}
    spans: list[tuple[str, int, int, int]] = []
    for file in files:
        result, topics, (first, last) = reindex_file(file, distro)
        done.append(result)
        spans.append((file.name, first, last, result.messages))
        for topic in topics:
            known = merged.setdefault(topic.name, _TopicRecord(
                topic.name, topic.type, topic.type_hash, topic.offered, 0))
            known.count += topic.count
    write_metadata(path, bag_metadata(list(merged.values()), spans, distro))
    return done
