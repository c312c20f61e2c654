"""ROS 2 bags in MCAP, laid out like `ros2 bag` writes them.

A bag is a directory holding `<name>_0.mcap` and `metadata.yaml`. The MCAP file follows
the ROS 2 profile: header profile `ros2`; one schema per type, encoding `ros2msg`, whose data
is the concatenated `.msg` definition; one channel per topic, message encoding `cdr`,
with `offered_qos_profiles` (YAML) and `topic_type_hash` metadata; messages are the CDR
bytes as they travelled, encapsulation header included, stamped with the receive time.
A `rosbag2` metadata record repeats `metadata.yaml` as `ros2 bag` does. Readers accept such
a directory (any writer's: rosbag2, rosbags, …) or a bare `.mcap` file.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader
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
    """Writes one bag; `write` may be called from any thread."""

    def __init__(self, directory: Path, store: TypeStore) -> None:
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

    def close(self) -> None:
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
        text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)
        (self.directory / METADATA_FILE).write_text(text, encoding="utf-8")

    def _metadata(self) -> dict[str, Any]:
        start = self._start_ns or 0
        duration = max(0, self._end_ns - start)
        count = self.message_count
        return {
            "version": METADATA_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [{
                "topic_metadata": {
                    "name": t.name, "type": t.type, "serialization_format": "cdr",
                    "offered_qos_profiles": t.offered,
                    "type_description_hash": t.type_hash,
                },
                "message_count": t.count,
            } for t in self._topics.values()],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.file_name],
            "files": [{
                "path": self.file_name,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": count,
            }],
            "custom_data": None,
            "ros_distro": self.store.distro,
        }


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
    loaded = yaml.safe_load(meta.read_text(encoding="utf-8")) or {}
    info = loaded.get("rosbag2_bagfile_information", {})
    return info if isinstance(info, dict) else {}


def _distro_of(path: Path, records: dict[str, dict[str, str]]) -> str:
    meta = path / METADATA_FILE
    if path.is_dir() and meta.is_file():
        distro = _load_metadata(meta).get("ros_distro")
        if distro:
            return str(distro)
    return records.get("rosbag2", {}).get("ROS_DISTRO", "") or "unknown"


class BagReader:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.files = bag_files(path)

    def summary(self) -> BagSummary:
        topics: dict[str, BagTopic] = {}
        start, end, count = 2**63, 0, 0
        records: dict[str, dict[str, str]] = {}
        for file in self.files:
            with file.open("rb") as stream:
                reader = make_reader(stream)
                summary = reader.get_summary()
                if summary is None:
                    raise BagError(f"'{file}' has no summary section (was recording cut?)")
                for rec in reader.iter_metadata():
                    records[rec.name] = dict(rec.metadata)
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
            with file.open("rb") as stream:
                reader = make_reader(stream)
                for schema, channel, message in reader.iter_messages(
                        topics=sorted(topics) if topics else None, log_time_order=True):
                    yield BagMessage(channel.topic, schema.name if schema else "",
                                     message.log_time, message.data)
