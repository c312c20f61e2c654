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

import contextlib
import fcntl
import heapq
import io
import itertools
import os
import re
import stat
import struct
import threading
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, cast

import lz4.frame
import yaml
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, ChunkIndex, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.summary import Summary
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
# A chunk (compressed or inflated) larger than this is refused, not read: a hostile file's
# chunk can claim, or inflate to, any size. rosbag2 closes a chunk at about 1 MiB; one message
# (a point cloud, an image) can make it larger, rarely near this.
CHUNK_LIMIT = 512 * 2**20
COMPRESSIONS = ("", "zstd", "lz4")
# A bag's metadata.yaml is a few KiB (a few MiB with thousands of topics); parsing YAML in
# Python takes about a second a MiB, so a larger one is refused, not parsed for minutes.
METADATA_LIMIT = 4 * 2**20


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


class _PlainLoader(yaml.SafeLoader):
    """Safe YAML without aliases. A bag's YAML (metadata.yaml, a channel's QoS) has none, and
    nine lines of nested aliases stand for a billion items that whoever walks them (str(),
    a loop) never finishes."""

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            raise yaml.composer.ComposerError(None, None, "an alias (*name): not accepted in "
                                              "a bag's YAML", self.peek_event().start_mark)
        return super().compose_node(parent, index)


def load_yaml(text: str) -> Any:
    """`text` parsed as plain YAML (no aliases); BagError when it is not."""
    try:
        return yaml.load(text, Loader=_PlainLoader)  # a SafeLoader
    except (yaml.YAMLError, RecursionError) as exc:  # RecursionError: [[[[… nested deeper
        raise BagError(_first_line(exc)) from None  # than Python's stack


def _int(value: Any, default: int) -> int:
    """`value` as an integer when it is one (or a string of one); else `default`."""
    if isinstance(value, bool):
        return default
    if isinstance(value, int):
        return value
    with contextlib.suppress(TypeError, ValueError):
        return int(str(value))
    return default


def _seconds(value: Any) -> float | None:
    if not isinstance(value, dict):
        return None
    sec, nsec = _int(value.get("sec"), 0), _int(value.get("nsec"), 0)
    if (sec, nsec) in ((_INFINITE["sec"], _INFINITE["nsec"]), (0, 0), (2147483647, 4294967295)):
        return None
    if sec < 0 or nsec < 0 or sec >= 2**31:  # no such QoS: unknown, as an infinite one
        return None
    return sec + nsec / 1e9


def parse_offered_qos(text: str | list[Any] | None) -> list[QosProfile]:
    """The profiles of a channel's `offered_qos_profiles` (YAML text or a parsed list). What
    is not a profile (bad YAML, a number, a list of strings, a field of the wrong type) counts
    as unknown: a bag's QoS is advice to `play`, which then uses the defaults."""
    return [_profile(item) for item in _offered_list(text)]


def _profile(item: dict[Any, Any]) -> QosProfile:
    history = str(item.get("history", "keep_last")).lower()
    depth = _int(item.get("depth"), 0)
    return QosProfile(
        history=History.KEEP_ALL if history == "keep_all" else History.KEEP_LAST,
        depth=depth if 0 < depth < 2**31 else 10,
        reliability=Reliability.BEST_EFFORT
        if str(item.get("reliability")).lower() == "best_effort" else Reliability.RELIABLE,
        durability=Durability.TRANSIENT_LOCAL
        if str(item.get("durability")).lower() == "transient_local" else Durability.VOLATILE,
        lifespan_s=_seconds(item.get("lifespan")),
        deadline_s=_seconds(item.get("deadline")),
    )


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
    (a thread of its own) what was written so far reaches the file and `metadata.yaml`.
    The file is locked (flock) while written: `reindex` refuses it.

    A write that fails (a full disk, a file size limit) ends the writing: the file is left
    as it was, its complete records readable and `reindex` completing it, and `failure` says
    what happened (`close` raises it). Writing on would append after a torn record, and
    buffer in memory what cannot reach the disk."""

    def __init__(self, directory: Path, store: TypeStore, *,
                 flush_period: float = FLUSH_PERIOD) -> None:
        if directory.exists():
            raise BagError(f"output folder '{directory}' already exists")
        directory.mkdir(parents=True)
        self.directory = directory
        self.file_name = f"{directory.name}_0.mcap"
        self.store = store
        self._stream = (directory / self.file_name).open("wb")
        with contextlib.suppress(OSError):  # a file system without locks: recorded unlocked
            fcntl.flock(self._stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._mcap = Writer(self._stream, compression=CompressionType.NONE)
        self._schemas: dict[str, int] = {}
        self._topics: dict[str, _TopicRecord] = {}
        self._lock = threading.Lock()
        self._start_ns: int | None = None
        self._end_ns = 0
        self._closed = False
        self.failure: BagError | None = None
        self._kept = 0  # messages on disk at the last flush
        with self._lock, self._failing_on_oserror():
            self._mcap.start(profile="ros2", library=f"rcan-rtps {__version__}")
        self.flush()  # the header and metadata.yaml on disk from the start
        if (failure := self.failure_so_far()) is not None:
            with contextlib.suppress(OSError):
                self._stream.close()
            raise failure
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_every, args=(flush_period,),
                                         name=f"bag-flush-{directory.name}", daemon=True)
        self._flusher.start()

    def failure_so_far(self) -> BagError | None:
        """`failure` (a call: mypy would take a check of the attribute just after a
        `_failing_on_oserror` block for the check it already made before)."""
        return self.failure

    @property
    def failed(self) -> bool:
        return self.failure_so_far() is not None

    @contextlib.contextmanager
    def _failing_on_oserror(self) -> Iterator[None]:
        """Within (under the lock): an OSError ends the writing, kept as `failure`."""
        try:
            yield
        except OSError as exc:
            if self.failure is None:
                self.failure = BagError(
                    f"could not write bag '{self.directory}' ({exc.strerror or exc}): "
                    f"recording stopped; the {self._kept} messages written before are in "
                    f"it, and `rcan-rtps bag reindex {self.directory}` completes it")

    def add_topic(self, name: str, type_name: str, offered: list[dict[str, Any]]) -> None:
        with self._lock:
            if name in self._topics or self.failure is not None:
                return
            schema_id = self._schemas.get(type_name)
            if schema_id is None:
                text = full_definition(type_name, self.store.message)
                with self._failing_on_oserror():
                    schema_id = self._mcap.register_schema(type_name, "ros2msg", text.encode())
                if self.failed:
                    return
                self._schemas[type_name] = schema_id
            type_hash = self.store.hash_of(type_name) if self.store.distro != "humble" else ""
            metadata = {"offered_qos_profiles": _qos_text(offered)}
            if type_hash:
                metadata["topic_type_hash"] = type_hash
            with self._failing_on_oserror():
                channel_id = self._mcap.register_channel(name, "cdr", schema_id, metadata)
                self._topics[name] = _TopicRecord(name, type_name, type_hash, offered,
                                                  channel_id)

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        with self._lock:
            if self._closed or self.failure is not None:
                return
            record = self._topics[topic]
            with self._failing_on_oserror():
                self._mcap.add_message(record.channel_id, log_time=log_time_ns, data=data,
                                       publish_time=log_time_ns, sequence=record.count)
            if self.failed:
                return
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
            if self._closed or self.failure is not None:
                return
            with self._failing_on_oserror():
                self._mcap.flush()
                write_metadata(self.directory, self._metadata())
                self._kept = self.message_count

    def _flush_every(self, period: float) -> None:
        while not self._stop.wait(period) and self.failure is None:
            self.flush()

    def close(self) -> None:
        self._stop.set()
        if self._flusher.is_alive() and self._flusher is not threading.current_thread():
            self._flusher.join()
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self.failure is None:
                with self._failing_on_oserror():
                    self._finish()
            with contextlib.suppress(OSError):  # what the disk refused is refused again
                self._stream.close()
        if self.failure is not None:
            raise self.failure

    def _finish(self) -> None:
        """The summary, indexes and closing magic; metadata.yaml counting every message."""
        info = self._metadata()
        self._mcap.add_metadata("rosbag2", {
            "serialized_metadata": yaml.safe_dump(info, sort_keys=False),
            "ROS_DISTRO": self.store.distro,
        })
        self._mcap.finish()
        self._stream.flush()
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
    with fresh_file(temporary) as stream:
        stream.write(text.encode("utf-8"))
    os.replace(temporary, directory / METADATA_FILE)


def fresh_file(path: Path) -> IO[bytes]:
    """A new file at `path`, for writing, whatever was there removed first and never opened:
    a bag folder is often someone else's (a tarball), and a link planted at a temporary's
    fixed name had the write land in its target (any file of the user running reindex), a
    FIFO there held the write for a reader that never came."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o666)
    return os.fdopen(fd, "wb")


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


@dataclass
class BagDamage:
    """Damage a bag's summary does not show (`BagReader.damage`)."""

    chunks: list[str] = field(default_factory=list)  # "<file> at byte N: why", one a chunk
    conflicts: list[str] = field(default_factory=list)  # "<file>: <id> is defined twice, …"


@dataclass(frozen=True)
class BagMessage:
    topic: str
    type: str
    log_time_ns: int
    data: bytes


def bag_files(path: Path) -> list[Path]:
    """The MCAP files of a bag directory (in metadata order) or the file itself."""
    if not path.exists():
        raise BagError(f"bag path '{path}' does not exist")
    if not path.is_dir():
        return [path]  # a regular file or not: opening it says (open_regular)
    meta = path / METADATA_FILE
    if meta.exists():
        names = metadata_file_names(_load_metadata(meta), meta)
        files = [path / Path(n).name for n in names]
        if files and all(f.is_file() for f in files):
            return files
    found = sorted(path.glob("*.mcap"))
    if not found:
        raise BagError(f"no storage could be initialized from '{path}': no .mcap file")
    return found


def open_regular(file: Path) -> IO[bytes]:
    """`file` opened for reading, when it is a regular file. A FIFO would block the open
    until someone writes to it, and a device (a symlink to /dev/zero) never ends: both are
    refused, the open made without blocking so the FIFO cannot hang it."""
    try:
        fd = os.open(file, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:
        raise BagError(f"cannot open '{file}': {exc.strerror}") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise BagError(f"'{file}' is not a regular file (a FIFO, device or socket is no bag)")
    return os.fdopen(fd, "rb")


def _load_metadata(meta: Path) -> dict[str, Any]:
    with open_regular(meta) as stream:
        raw = stream.read(METADATA_LIMIT + 1)
    if len(raw) > METADATA_LIMIT:
        raise BagError(f"'{meta}' is not a bag's metadata.yaml: larger than "
                       f"{METADATA_LIMIT // 2**20} MiB")
    try:
        loaded = load_yaml(raw.decode("utf-8")) or {}
    except (BagError, UnicodeDecodeError) as exc:
        raise BagError(f"'{meta}' is not a bag's metadata.yaml: {_first_line(exc)}") from None
    info = loaded.get("rosbag2_bagfile_information", {}) if isinstance(loaded, dict) else {}
    return info if isinstance(info, dict) else {}


def metadata_file_names(info: dict[str, Any], meta: Path) -> list[str]:
    """The `relative_file_paths` of a loaded metadata.yaml: a list of names, or none."""
    names = info.get("relative_file_paths")
    if names is None:
        return []
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise BagError(f"'{meta}' is not a bag's metadata.yaml: relative_file_paths is not "
                       "a list of file names")
    return names


def metadata_distro(info: dict[str, Any]) -> str:
    """The `ros_distro` of a loaded metadata.yaml when it is a name; else ''."""
    distro = info.get("ros_distro")
    return distro if isinstance(distro, str) and len(distro) < 64 else ""


def _distro_of(path: Path, records: dict[str, dict[str, str]]) -> str:
    meta = path / METADATA_FILE
    if path.is_dir() and meta.exists():
        distro = metadata_distro(_load_metadata(meta))
        if distro:
            return distro
    return records.get("rosbag2", {}).get("ROS_DISTRO", "")[:64] or "unknown"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _bag_of(file: Path) -> Path:
    """What to name in the reindex hint: the bag folder a file is in, or the file."""
    return file.parent if (file.parent / METADATA_FILE).is_file() else file


def check_mcap(file: Path) -> None:
    """Fails with what is wrong when `file` cannot be an MCAP file at all."""
    with open_regular(file) as stream:
        head = stream.read(len(MCAP_MAGIC))
    if not head:
        raise BagError(f"'{file}' is empty (did the recorder die before writing anything?)")
    if head != MCAP_MAGIC[:len(head)] or len(head) < len(MCAP_MAGIC):
        raise BagError(f"'{file}' is not an MCAP file")


def _damaged(file: Path, exc: BaseException) -> BagError:
    return BagError(f"'{file}' is damaged or cut short ({_first_line(exc)}); "
                    + REINDEX_HINT.format(bag=_bag_of(file)))


# Reading a damaged file fails in the mcap library's parsing (struct, sizes, decoding).
_PARSE_ERRORS = (McapError, struct.error, ValueError, IndexError, KeyError, EOFError, OverflowError,
                 zstandard.ZstdError)


class Definitions:
    """The schemas and channels of a file by id, as its records define them: the first
    definition of an id is kept; one repeated as it was (a chunked file's summary repeats
    them all) is nothing; one under a known id with other contents is a conflict. A channel
    whose id, or its schema's, was defined otherwise cannot say which topic (or type) its
    messages are of."""

    def __init__(self) -> None:
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        # ("channel"|"schema", id): the first name (topic, type) and the other
        self.conflicts: dict[tuple[str, int], tuple[str, str]] = {}

    def add(self, record: Any) -> None:
        if isinstance(record, Schema):
            self._define(self.schemas, "schema", record, record.name)
        elif isinstance(record, Channel):
            self._define(self.channels, "channel", record, record.topic)

    def _define(self, known: dict[int, Any], kind: str, record: Any, name: str) -> None:
        first = known.setdefault(record.id, record)
        if first != record and (kind, record.id) not in self.conflicts:
            self.conflicts[kind, record.id] = (
                first.name if kind == "schema" else first.topic, name)

    def conflict_of(self, channel_id: int) -> str:
        """Why the messages of `channel_id` cannot be attributed; '' when they can."""
        channel = self.channels.get(channel_id)
        return self.conflict_of_id("channel", channel_id) or \
            self.conflict_of_id("schema", channel.schema_id if channel else -1)

    def conflict_of_id(self, kind: str, key: int) -> str:
        """The words for a `kind` ("channel", "schema") id defined twice; '' if it is not."""
        if (kind, key) not in self.conflicts:
            return ""
        was, other = self.conflicts[kind, key]
        return f"{kind} id {key} is defined twice, as '{_printable(was)}' and as " \
            f"'{_printable(other)}'"

    def topics_of(self, channel_id: int) -> set[str]:
        """The topics a channel id is defined with (two when they conflict)."""
        channel = self.channels.get(channel_id)
        other = self.conflicts.get(("channel", channel_id), ("", ""))[1]
        return {t for t in (channel.topic if channel else "", other) if t}

    def refuse(self, file: Path, channel_id: int) -> BagError:
        return BagError(f"'{file}': {self.conflict_of(channel_id)}, so its messages cannot "
                        "be told apart: not played (`rcan-rtps bag reindex` keeps the first "
                        "definition and leaves out the messages after the second)")


def _printable(text: str) -> str:
    return text[:64].encode("unicode_escape").decode("ascii")


def _summary_definitions(stream: IO[bytes], file: Path) -> Definitions:
    """The schemas and channels of a closed file's summary section, as `Definitions`. The
    caller has refused a summary section holding a chunk (`_check_summary_section`): the
    reader below would inflate it."""
    found = Definitions()
    summary_start = _summary_start(stream)
    if summary_start is None:
        return found
    size = os.fstat(stream.fileno()).st_size
    stream.seek(summary_start)
    records = StreamReader(BoundedFile(stream, size - FOOTER_TAIL.size), skip_magic=True,  # type: ignore[arg-type]
                           record_size_limit=CHUNK_LIMIT).records
    try:
        for record in records:
            found.add(record)
    except EndOfFile:  # the footer, left out: the summary's end
        pass
    except _PARSE_ERRORS as exc:
        raise _damaged(file, exc) from None
    return found


def _summary_start(stream: IO[bytes]) -> int | None:
    """Where a closed file's summary section starts (its data section's end); None when
    its footer says it has none, or there is no footer."""
    tail = FOOTER_TAIL.size
    size = os.fstat(stream.fileno()).st_size
    if size < len(MCAP_MAGIC) + tail:
        return None
    stream.seek(size - tail)
    opcode, _, summary_start, _, _, magic = FOOTER_TAIL.unpack(stream.read(tail))
    if opcode != 0x02 or magic != MCAP_MAGIC or not 0 < summary_start < size - tail:
        return None
    return int(summary_start)


def _check_summary_section(stream: IO[bytes], file: Path) -> None:
    """Refuses a summary section holding a chunk (MCAP's has none: a footer pointing at the
    data section makes one), walked head by head as the mcap library walks it: the library
    inflates a chunk it meets there to what it claims, before anything can check it. Leaves
    the stream at its start."""
    start = _summary_start(stream)
    size = os.fstat(stream.fileno()).st_size
    offset = size if start is None else start
    while offset + RECORD_HEAD.size <= size:  # (each step moves on by 9 B at least)
        stream.seek(offset)
        opcode, length = RECORD_HEAD.unpack(stream.read(RECORD_HEAD.size))
        if opcode == 0x06:
            raise BagError(f"'{file}' is damaged: its summary section holds a chunk (at byte "
                           f"{offset}); " + REINDEX_HINT.format(bag=_bag_of(file)))
        offset += RECORD_HEAD.size + length
    stream.seek(0)  # where the mcap library's reader starts


# Records of the data section `bag info` reads: schemas and channels, and chunks (which hold
# them as recorders write them); messages and indexes are stepped over.
_DEFINING_OPCODES = {0x03, 0x04, 0x06}


def _check_data_section(stream: IO[bytes], file: Path, found: BagDamage) -> None:
    """Adds to `found` the chunks of `file` whose CRC does not match or that do not inflate,
    and the summary's definitions that the data section's contradict."""
    size = os.fstat(stream.fileno()).st_size
    end = _summary_start(stream) or size
    in_data = Definitions()
    for offset, length in _heads(stream, len(MCAP_MAGIC), end):
        if _opcode_at(stream, offset) not in _DEFINING_OPCODES:
            continue
        if length > CHUNK_LIMIT:
            found.chunks.append(f"{file.name} at byte {offset}: a record of {length} B, over "
                                f"the {CHUNK_LIMIT >> 20} MiB read")
            continue
        stream.seek(offset)
        try:
            for record in _checked_records(stream.read(RECORD_HEAD.size + length), file):
                in_data.add(record)
        except BagError as exc:
            found.chunks.append(f"{file.name} at byte {offset}: {_unnamed(exc, file)}")
    _check_summary_section(stream, file)
    in_summary = _summary_definitions(stream, file)
    for record in [*in_summary.schemas.values(), *in_summary.channels.values()]:
        in_data.add(record)
    found.conflicts += [f"{file.name}: " + in_data.conflict_of_id(kind, key)
                        + " (the summary's differs from the data section's)"
                        for kind, key in in_data.conflicts]


def _opcode_at(stream: IO[bytes], offset: int) -> int:
    stream.seek(offset)
    return stream.read(1)[0]


def _checked_records(raw: bytes, file: Path) -> list[Any]:
    """The record `raw` is (a chunk: the records it holds, inflated and its CRC checked);
    BagError when it does not parse, inflate or check."""
    try:
        record = next(StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True,
                                   record_size_limit=CHUNK_LIMIT).records)
    except (StopIteration, EndOfFile, *_PARSE_ERRORS) as exc:
        raise BagError(f"'{file}' is damaged: a record that does not parse "
                       f"({_first_line(exc)})") from None
    if not isinstance(record, Chunk):
        return [record]
    data = inflate(record, file)
    if record.uncompressed_crc and zlib.crc32(data) != record.uncompressed_crc:
        raise BagError(f"'{file}' is damaged: a chunk's CRC does not match")
    return list(_records_of(data, file))


FOOTER_TAIL = struct.Struct("<BQQQI8s")  # the footer record and the closing magic


class BagReader:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.files = bag_files(path)

    def summary(self) -> BagSummary:
        topics: dict[str, BagTopic] = {}
        start, end, count = 2**63, 0, 0
        records: dict[str, dict[str, str]] = {}
        for file in self.files:
            summary = _file_summary(file, records)
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

    def damage(self) -> BagDamage:
        """What `summary` cannot see, read from each file's data section (its chunks read
        once, inflated one at a time): chunks whose CRC does not match or that do not
        inflate, and summaries whose schemas or channels are not the data section's."""
        found = BagDamage()
        for file in self.files:
            check_mcap(file)
            with open_regular(file) as stream:
                _check_data_section(stream, file, found)
        return found

    def messages(self, topics: set[str] | None = None) -> Iterator[BagMessage]:
        """Every message in receive-time order (per file, files in order); of `topics` only,
        when given (an empty set: none, where the library would read all)."""
        if topics is not None and not topics:
            return
        for file in self.files:
            check_mcap(file)
            with open_regular(file) as stream:
                _check_summary_section(stream, file)
                reader = make_reader(_bounded(stream))
                try:
                    summary = reader.get_summary()
                    if summary is not None:
                        check_chunks(BoundedFile(stream), summary, file)
                except _PARSE_ERRORS as exc:
                    raise _damaged(file, exc) from None
                # the library keeps the last of two definitions of an id: read them here
                definitions = _summary_definitions(stream, file)
                _refuse_conflicts(definitions, topics, file)
                if summary is None or not summary.chunk_indexes:
                    # the library would read the data section, its chunks unchecked
                    yield from _unindexed_messages(stream, definitions, topics, file)
                    continue
                yield from _indexed_messages(stream, summary, definitions, topics, file)


def _refuse_conflicts(definitions: Definitions, topics: set[str] | None, file: Path) -> None:
    """Fails when a channel played (of `topics`; all: None) cannot be attributed."""
    for channel_id in definitions.channels:
        if definitions.conflict_of(channel_id) and (
                topics is None or definitions.topics_of(channel_id) & topics):
            raise definitions.refuse(file, channel_id)


def _file_summary(file: Path, records: dict[str, dict[str, str]]) -> Summary:
    """The summary section of `file`; its metadata records into `records`."""
    check_mcap(file)
    try:
        with open_regular(file) as stream:
            _check_summary_section(stream, file)
            reader = make_reader(_bounded(stream))
            summary = reader.get_summary()
            if summary is None:
                raise BagError(f"'{file}' has no summary section (was the recording "
                               "cut short?); " + REINDEX_HINT.format(bag=_bag_of(file)))
            for rec in _metadata_records(stream, summary, file):
                records[rec.name] = dict(rec.metadata)
    except _PARSE_ERRORS as exc:
        raise _damaged(file, exc) from None
    return summary


METADATA_OPCODE = 0x0C


def _metadata_records(stream: IO[bytes], summary: Summary, file: Path) -> Iterator[Metadata]:
    """The metadata records the summary's metadata indexes point at, each read once. The
    mcap library's own read parses whatever an index points at: a chunk there, it inflated
    to what the chunk claims."""
    bounded = BoundedFile(stream)
    for offset in dict.fromkeys(index.offset for index in summary.metadata_indexes):
        bounded.seek(offset)
        head = bounded.read(RECORD_HEAD.size)
        if len(head) < RECORD_HEAD.size or head[0] != METADATA_OPCODE:
            raise BagError(f"'{file}' is damaged: a metadata index points at no metadata "
                           "record; " + REINDEX_HINT.format(bag=_bag_of(file)))
        bounded.seek(offset)
        record = next(StreamReader(cast(IO[bytes], bounded), skip_magic=True,
                                   emit_chunks=True, record_size_limit=CHUNK_LIMIT).records)
        if isinstance(record, Metadata):
            yield record


def _bounded(stream: IO[bytes]) -> IO[bytes]:
    """`stream` as a BoundedFile, typed as the file the mcap library asks for."""
    return cast(IO[bytes], BoundedFile(stream))  # it has the calls the library makes


def _unindexed_messages(stream: IO[bytes], definitions: Definitions,
                        topics: set[str] | None, file: Path) -> Iterator[BagMessage]:
    """The messages of a file without chunk indexes, in file order, each chunk checked and
    inflated here (within CHUNK_LIMIT)."""
    stream.seek(0)
    for record in data_records(stream, file):
        definitions.add(record)
        if isinstance(record, Message) and record.channel_id in definitions.channels:
            channel = definitions.channels[record.channel_id]
            if topics is None or definitions.topics_of(record.channel_id) & topics:
                if definitions.conflict_of(record.channel_id):
                    raise definitions.refuse(file, record.channel_id)
                schema = definitions.schemas.get(channel.schema_id)
                yield BagMessage(channel.topic, schema.name if schema else "",
                                 record.log_time, record.data)


# The messages play holds at once to put overlapping chunks in receive-time order. A
# recorder's chunks follow each other in time (two overlap by a few messages); a hostile
# file's chunks, each within CHUNK_LIMIT, may all start at once, and be zstd bombs.
HELD_LIMIT = 2 * CHUNK_LIMIT


def _indexed_messages(stream: IO[bytes], summary: Summary, definitions: Definitions,
                      topics: set[str] | None, file: Path) -> Iterator[BagMessage]:
    """The messages of a file's indexed chunks in receive-time order, as the mcap library
    orders them (a chunk is opened when its first time is due), each chunk read and inflated
    here within CHUNK_LIMIT: the library allocates what a chunk claims. The schemas and
    channels inside the chunks are checked against the summary's (`definitions`)."""
    due: list[tuple[int, int, int, int, Any]] = []  # (time, chunk, index, serial, what)
    serial = itertools.count()
    # one chunk indexed twice or more (a hostile summary) is read once: its messages held
    # and played once per index, memory was the chunk's times the summary's count of indexes
    by_offset = {index.chunk_start_offset: index for index in summary.chunk_indexes
                 if _may_hold(index, definitions, topics)}
    for index in by_offset.values():
        heapq.heappush(due, (index.message_start_time, index.chunk_start_offset, -1,
                             next(serial), index))
    held = 0  # bytes of the messages waiting in `due`
    while due:
        *_, item = heapq.heappop(due)
        if isinstance(item, Message):
            held -= len(item.data)
            channel = definitions.channels[item.channel_id]
            schema = definitions.schemas.get(channel.schema_id)
            yield BagMessage(channel.topic, schema.name if schema else "", item.log_time,
                             item.data)
            continue
        for at, record in enumerate(_indexed_chunk(stream, item, file)):
            definitions.add(record)
            if not isinstance(record, Message) or record.channel_id not in definitions.channels:
                continue
            if topics is None or definitions.topics_of(record.channel_id) & topics:
                if definitions.conflict_of(record.channel_id):
                    raise definitions.refuse(file, record.channel_id)
                heapq.heappush(due, (record.log_time, item.chunk_start_offset, at,
                                     next(serial), record))
                held += len(record.data)
        if held > HELD_LIMIT:
            raise BagError(f"'{file}' has chunks overlapping in time that hold more than "
                           f"{HELD_LIMIT >> 20} MiB of messages at once (a damaged or "
                           "hostile file): not played")


def _may_hold(index: ChunkIndex, definitions: Definitions, topics: set[str] | None) -> bool:
    """Whether the chunk of `index` may hold messages of `topics` (all: None), as its index's
    channels say (an index that names none may hold any)."""
    return topics is None or not index.message_index_offsets or any(
        definitions.topics_of(channel_id) & topics
        for channel_id in index.message_index_offsets)


def _indexed_chunk(stream: IO[bytes], index: ChunkIndex, file: Path) -> list[Any]:
    """The records of the chunk `index` points at (check_chunks checked its head)."""
    bounded = BoundedFile(stream)
    try:
        bounded.seek(index.chunk_start_offset + RECORD_HEAD.size)
        chunk = Chunk.read(ReadDataStream(cast(IO[bytes], bounded)))
    except _PARSE_ERRORS as exc:
        raise _damaged(file, exc) from None
    return list(_records_of(inflate(chunk, file), file))


# -- chunks, within limits ------------------------------------------------------------
CHUNK_FIELDS = struct.Struct("<BQQQQI")  # opcode, length, start, end, uncompressed size, crc


def check_chunks(stream: BoundedFile, summary: Summary, file: Path) -> None:
    """Refuses a file whose chunk indexes point at anything but a chunk that fits in the
    file and claims at most CHUNK_LIMIT, before any message is played (each is inflated,
    within its claim, when it is read)."""
    for index in summary.chunk_indexes:
        if index.chunk_start_offset >= stream.end:
            raise BagError(f"'{file}' is damaged: a chunk index points past its end")
        stream.seek(index.chunk_start_offset)
        _chunk_head(stream, stream.end - index.chunk_start_offset, file)


def _chunk_head(stream: BoundedFile, room: int, file: Path) -> Chunk:
    """The fixed fields of the chunk record at the stream's position (its data left out),
    checked against the `room` left in the file and CHUNK_LIMIT."""
    head = stream.read(CHUNK_FIELDS.size)
    if len(head) < CHUNK_FIELDS.size:
        raise BagError(f"'{file}' is damaged: a chunk index points past its end")
    opcode, length, start, end, uncompressed, crc = CHUNK_FIELDS.unpack(head)
    if opcode != 0x06:
        raise BagError(f"'{file}' is damaged: a chunk index points at no chunk")
    if length > room - RECORD_HEAD.size:
        raise BagError(f"'{file}' is damaged: a chunk runs past its end")
    compression = _short_string(stream, file)
    (data_length,) = struct.unpack("<Q", stream.read(8).ljust(8, b"\xff"))
    if data_length > length:
        raise BagError(f"'{file}' is damaged: a chunk's data runs past the chunk")
    chunk = Chunk(compression=compression, data=b"", message_end_time=end,
                  message_start_time=start, uncompressed_crc=crc,
                  uncompressed_size=uncompressed)
    check_chunk_limits(chunk, length, file)
    return chunk


def _short_string(stream: BoundedFile, file: Path) -> str:
    (length,) = struct.unpack("<I", stream.read(4).ljust(4, b"\xff"))
    text = stream.read(length) if length <= 16 else b"?"
    try:
        return text.decode("ascii")
    except UnicodeDecodeError:
        raise BagError(f"'{file}' is damaged: a chunk's compression is not a name") from None


def check_chunk_limits(chunk: Chunk, record_length: int, file: Path) -> None:
    if chunk.compression not in COMPRESSIONS:
        raise BagError(f"'{file}' has a chunk compressed with {chunk.compression[:16]!r}: "
                       "not one MCAP names (zstd, lz4)")
    if max(record_length, chunk.uncompressed_size) > CHUNK_LIMIT:
        raise BagError(f"'{file}' has a chunk of {max(record_length, chunk.uncompressed_size)}"
                       f" B, over the {CHUNK_LIMIT // 2**20} MiB this tool reads (a damaged "
                       "or hostile file)")


def inflate(chunk: Chunk, file: Path) -> bytes:
    """The records a chunk holds, inflated, never to more than the size it claims (itself
    within CHUNK_LIMIT). Inflated a block at a time: the memory taken is what the data
    inflates to, not what the chunk claims (a chunk of 500 B may claim 500 MiB)."""
    check_chunk_limits(chunk, len(chunk.data), file)
    claimed = chunk.uncompressed_size
    try:
        if chunk.compression == "zstd":
            data = _inflate_zstd(chunk.data, claimed)
        elif chunk.compression == "lz4":
            data = _inflate_lz4(chunk.data, claimed, file)
        else:
            data = chunk.data
    except (zstandard.ZstdError, RuntimeError) as exc:  # lz4 raises RuntimeError
        raise BagError(f"'{file}' is damaged: a chunk does not inflate "
                       f"({_first_line(exc)})") from None
    if len(data) != claimed:
        raise BagError(f"'{file}' is damaged: a chunk inflates to "
                       f"{'more' if len(data) > claimed else 'less'} than the "
                       f"{claimed} B it claims")
    return data


INFLATE_BLOCK = 1 << 20  # what one step of inflating may add


def _inflate_zstd(data: bytes, claimed: int) -> bytes:
    """zstd frames inflated to at most `claimed` + 1 bytes, a block at a time (a read of
    `claimed` bytes at once allocates them whatever the frames hold)."""
    reader = zstandard.ZstdDecompressor().stream_reader(data, read_across_frames=True)
    inflated = bytearray()
    while len(inflated) <= claimed:
        block = reader.read(min(INFLATE_BLOCK, claimed + 1 - len(inflated)))
        if not block:
            break
        inflated += block
    return bytes(inflated)


def _inflate_lz4(data: bytes, claimed: int, file: Path) -> bytes:
    """An LZ4 frame inflated to at most `claimed` + 1 bytes, a block at a time; the frame
    must end there (a cut frame is damage)."""
    decompressor = lz4.frame.LZ4FrameDecompressor()
    inflated = bytearray(decompressor.decompress(data, max_length=min(INFLATE_BLOCK,
                                                                        claimed + 1)))
    while len(inflated) <= claimed and not decompressor.eof and not decompressor.needs_input:
        inflated += decompressor.decompress(b"", max_length=min(
            INFLATE_BLOCK, claimed + 1 - len(inflated)))
    if len(inflated) <= claimed and not decompressor.eof:
        raise BagError(f"'{file}' is damaged: a chunk's LZ4 frame is cut short")
    return bytes(inflated)


class BoundedFile:
    """A binary file as the mcap library reads it, seen up to `end` (its size): a read never
    asks for more than is left, so a length field of 2^62 costs what the file holds, not an
    allocation of 2^62 bytes; a seek before the start or past `end` is a file cut short."""

    def __init__(self, stream: IO[bytes], end: int | None = None) -> None:
        self.stream = stream
        self.end = os.fstat(stream.fileno()).st_size if end is None else end

    def read(self, size: int | None = -1) -> bytes:
        left = max(0, self.end - self.stream.tell())
        return self.stream.read(left if size is None or size < 0 else min(size, left))

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.stream.tell(), io.SEEK_END: self.end}[whence]
        if not 0 <= base + offset <= self.end:
            raise EndOfFile()  # an offset in a damaged file: the reader's "cut short"
        return self.stream.seek(base + offset)

    def tell(self) -> int:
        return self.stream.tell()

    def seekable(self) -> bool:
        return True

    def readable(self) -> bool:
        return True


def data_records(stream: IO[bytes], file: Path, end: int | None = None) -> Iterator[Any]:
    """The records of an MCAP file from its start up to `end` (its end: None), chunks opened
    here within CHUNK_LIMIT; ends quietly where the bytes end."""
    stream.seek(0)
    source: Any = BoundedFile(stream, end)
    found = StreamReader(source, emit_chunks=True, record_size_limit=CHUNK_LIMIT).records
    while True:
        try:
            record = next(found)
        except (StopIteration, EndOfFile):
            return
        except _PARSE_ERRORS as exc:
            raise BagError(f"'{file}' is damaged inside its data ({_first_line(exc)})") \
                from None
        if isinstance(record, Chunk):
            yield from _chunk_records(record, file)
        else:
            yield record


def _chunk_records(chunk: Chunk, file: Path) -> Iterator[Any]:
    yield from _records_of(inflate(chunk, file), file)


def _records_of(data: bytes, file: Path) -> Iterator[Any]:
    """The records of a chunk's inflated `data`; one that does not parse is a BagError, and
    so is a chunk in it (MCAP has none: the library would inflate it to what it claims)."""
    found = StreamReader(io.BytesIO(data), skip_magic=True, emit_chunks=True,
                         record_size_limit=CHUNK_LIMIT).records
    while True:
        try:
            record = next(found)
        except (StopIteration, EndOfFile):
            return
        except _PARSE_ERRORS as exc:
            raise BagError(f"'{file}' is damaged inside a chunk ({_first_line(exc)})") \
                from None
        if isinstance(record, Chunk):
            raise BagError(f"'{file}' is damaged inside a chunk (a chunk in it)")
        yield record


# -- reindex ------------------------------------------------------------------------
@dataclass
class ReindexedFile:
    path: Path
    messages: int
    dropped_bytes: int  # the torn record(s) at the end, left out
    unattributed: int = 0  # messages of a channel the file never defines: left out
    conflicted: int = 0  # messages of a channel after its id was defined again otherwise
    conflicts: list[str] = field(default_factory=list)  # ids defined again: the first kept
    # damage in the middle stepped over (byte ranges), what follows it kept
    skipped: list[tuple[int, int]] = field(default_factory=list)
    unreadable: int = 0  # whole records (chunks) whose contents could not be read: left out
    unreadable_why: str = ""  # the first one's reason


# Record types of the MCAP spec (Header 0x01 … DataEnd 0x0F): a head with another opcode is
# no record of this file's.
MCAP_OPCODES = range(0x01, 0x10)
# Past a damaged record, how far reindex looks for the next whole one, and how many whole
# records in a row (unless the file ends with them) make one: a head's length must fit the
# file, which 8 bytes of garbage pass about as often as their 3 high bytes are 0.
RESYNC_LIMIT = 64 * 2**20
RESYNC_RECORDS = 8
# A head that may start a record: a known opcode, and a length under 2^40 (1 TiB).
_CANDIDATE = re.compile(rb"[\x01-\x0f](?=.....\x00\x00\x00)", re.DOTALL)


@dataclass
class RecordLayout:
    """Where a file's whole records are (`spans`: byte ranges of records one after the other),
    the damage between them that was stepped over (`skipped`), and the torn bytes at its end
    that start no whole record (`torn`)."""

    spans: list[tuple[int, int]]
    skipped: list[tuple[int, int]]
    torn: int


def record_layout(stream: IO[bytes]) -> RecordLayout:
    """The file's records by their heads alone: a killed writer's torn last record is left
    out; damage in the middle (a head that is no record's) is stepped over to the next run of
    whole records, as far as RESYNC_LIMIT, so that what follows it is kept."""
    size = os.fstat(stream.fileno()).st_size
    spans: list[tuple[int, int]] = []
    skipped: list[tuple[int, int]] = []
    start = len(MCAP_MAGIC)
    while True:
        end, _ = _whole_records(stream, start, size)
        if _ends_here(stream, end, size):
            spans.append((start, size))
            return RecordLayout(spans, skipped, 0)
        spans.append((start, end))
        resume = _next_records(stream, end, size)
        if resume is None:
            return RecordLayout(spans, skipped, size - end)
        skipped.append((end, resume))
        start = resume


def _heads(stream: IO[bytes], offset: int, end: int) -> Iterator[tuple[int, int]]:
    """(offset, length) of each whole record of a known type from `offset`, up to the first
    head that is none (or to `end`); read by heads alone."""
    while offset + RECORD_HEAD.size <= end:
        stream.seek(offset)
        opcode, length = RECORD_HEAD.unpack(stream.read(RECORD_HEAD.size))
        if opcode not in MCAP_OPCODES or length > end - offset - RECORD_HEAD.size:
            return
        yield offset, length
        offset += RECORD_HEAD.size + length


def _whole_records(stream: IO[bytes], offset: int, size: int,
                   at_most: int | None = None) -> tuple[int, int]:
    """Whole records of known types from `offset` (at most `at_most`): where they end, and
    how many there are."""
    count = 0
    for at, length in _heads(stream, offset, size):
        if at_most is not None and count == at_most:
            break
        offset, count = at + RECORD_HEAD.size + length, count + 1
    return offset, count


def _ends_here(stream: IO[bytes], offset: int, size: int) -> bool:
    """Whether the file ends at `offset`, or with only the closing magic after it."""
    if offset == size:
        return True
    stream.seek(offset)
    return stream.read(len(MCAP_MAGIC) + 1) == MCAP_MAGIC


def _next_records(stream: IO[bytes], damaged: int, size: int) -> int | None:
    """Where whole records start again after the damaged head at `damaged`: RESYNC_RECORDS
    of them in a row, or fewer that end the file. None within RESYNC_LIMIT: the rest is
    taken for a torn tail."""
    window_end = min(size, damaged + 1 + RESYNC_LIMIT)
    block = 1 << 20
    for base in range(damaged + 1, window_end, block):
        stream.seek(base)
        data = stream.read(min(block, window_end - base) + RECORD_HEAD.size - 1)
        for found in _CANDIDATE.finditer(data):
            at = base + found.start()
            if at >= window_end:
                break
            end, count = _whole_records(stream, at, size, RESYNC_RECORDS)
            if count == RESYNC_RECORDS or (count and _ends_here(stream, end, size)):
                return at
    return None


@contextlib.contextmanager
def _not_being_recorded(file: Path) -> Iterator[IO[bytes]]:
    """`file` open, and locked as a recorder locks the file it writes (BagWriter): a file
    still being recorded is refused. Replaced while its recorder goes on writing, all it
    wrote after would be lost."""
    check_mcap(file)
    with open_regular(file) as stream:
        try:
            fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise BagError(f"'{file}' is being recorded (its recorder holds it); reindex it "
                           "once the recording ends") from None
        except OSError:  # a file system without locks: no recorder can have locked it either
            pass
        yield stream


def reindex_file(file: Path, distro: str) -> tuple[ReindexedFile, list[_TopicRecord],
                                                    tuple[int, int]]:
    """Rewrites `file` as a complete MCAP (summary, chunk and message indexes, statistics)
    holding every message its complete records hold; the original is replaced in one step."""
    with _not_being_recorded(file) as source:
        layout = record_layout(source)
        losses = _Losses()
        temporary = file.with_name(f".{file.name}.reindex")
        try:
            with fresh_file(temporary) as stream:
                writer = Writer(stream, compression=CompressionType.NONE)
                result = _rewrite(salvaged_records(source, file, layout, losses), writer,
                                  distro, file)
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise
        os.replace(temporary, file)
    count, topics, (first, last), left = result
    return ReindexedFile(file, count, layout.torn, *left, skipped=layout.skipped,
                         unreadable=losses.records, unreadable_why=losses.first), \
        topics, (first, last)


@dataclass
class _Losses:
    records: int = 0  # framed records that do not parse; chunks that do not inflate or check
    first: str = ""  # why the first was left out

    def add(self, why: str) -> None:
        self.records += 1
        self.first = self.first or why


def salvaged_records(stream: IO[bytes], file: Path, layout: RecordLayout,
                     losses: _Losses) -> Iterator[Any]:
    """The records of `layout`'s spans, each parsed on its own (chunks opened, within
    CHUNK_LIMIT): one whose contents do not parse, or a chunk that does not inflate or
    whose CRC differs, is counted in `losses` and left out, and the others still come."""
    for start, end in layout.spans:  # (a complete file's span ends at its closing magic)
        for offset, length in _heads(stream, start, end):  # (each head read after a seek)
            if length > CHUNK_LIMIT:
                losses.add(f"a record of {length} B, over the {CHUNK_LIMIT >> 20} MiB read")
                continue
            stream.seek(offset)
            yield from _salvaged(stream.read(RECORD_HEAD.size + length), file, losses)


def _salvaged(raw: bytes, file: Path, losses: _Losses) -> list[Any]:
    """The record `raw` is (a chunk: the records it holds, its CRC checked), or [] and one
    more loss."""
    try:
        return _checked_records(raw, file)
    except BagError as exc:  # the file is named in the line reindex prints: said once
        losses.add(_unnamed(exc, file))
    return []


def _unnamed(exc: BagError, file: Path) -> str:
    """What `exc` says of `file`, without naming it (the line it goes in names it)."""
    return str(exc).replace(f"'{file}' is damaged: ", "").replace(f"'{file}' is ", "") \
        .replace(f"'{file}' ", "")


def _rewrite(records: Iterator[Any], writer: Writer, distro: str, file: Path
             ) -> tuple[int, list[_TopicRecord], tuple[int, int], tuple[int, int, list[str]]]:
    """Writes `records` anew with `writer` (summary and indexes at the end): the message
    count, the topics, the first and last receive times, and what was left out: messages of
    no channel; messages of a channel after its id, or its schema's, was defined again
    otherwise (which of the two they are of, none can tell); the words for those
    redefinitions, of which the first definition is kept."""
    topics: dict[int, _TopicRecord] = {}
    schema_ids: dict[int, int] = {}
    schema_names: dict[int, str] = {}
    channels: dict[int, int] = {}
    definitions = Definitions()
    first, last, count, unattributed, conflicted = 2**63, 0, 0, 0, 0
    profile, library = "ros2", f"rcan-rtps {__version__} (reindex)"
    header = next(records, None)
    if header is not None and hasattr(header, "profile"):
        profile = header.profile or profile
    writer.start(profile=profile, library=library)
    for record in records:
        definitions.add(record)  # (the summary repeats them as they were: not a conflict)
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
        elif isinstance(record, Message) and record.channel_id not in channels:
            unattributed += 1
        elif isinstance(record, Message) and definitions.conflict_of(record.channel_id):
            conflicted += 1
        elif isinstance(record, Message):
            writer.add_message(channels[record.channel_id], log_time=record.log_time,
                               data=record.data, publish_time=record.publish_time,
                               sequence=record.sequence)
            topics[record.channel_id].count += 1
            first, last = min(first, record.log_time), max(last, record.log_time)
            count += 1
        elif isinstance(record, Metadata) and record.name != "rosbag2":
            writer.add_metadata(record.name, dict(record.metadata))
    info = bag_metadata(list(topics.values()), [(file.name, first, last, count)], distro)
    writer.add_metadata("rosbag2", {
        "serialized_metadata": yaml.safe_dump(info, sort_keys=False), "ROS_DISTRO": distro})
    writer.finish()
    said = [definitions.conflict_of_id(kind, key) for kind, key in definitions.conflicts]
    return count, list(topics.values()), (first, last), (unattributed, conflicted, said)


def _offered_list(text: str | list[Any] | None) -> list[dict[str, Any]]:
    """The profiles of an `offered_qos_profiles` (YAML text or a parsed list) as mappings;
    what is not one is left out (bad YAML, a number, a list of strings: none)."""
    try:
        loaded = load_yaml(text) if isinstance(text, str) and text else text
    except BagError:
        return []
    return [item for item in loaded if isinstance(item, dict)] if isinstance(loaded, list) \
        else []


def _old_distro(meta: Path) -> str:
    """The distro the metadata.yaml being replaced names; '' when it names none or is not a
    bag's metadata.yaml at all (reindex writes it anew either way)."""
    try:
        return metadata_distro(_load_metadata(meta)) if meta.exists() else ""
    except BagError:
        return ""


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
    distro = distro or _old_distro(meta) or "unknown"
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
