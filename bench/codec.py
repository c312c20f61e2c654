"""Encode/decode cost per sample: our codec vs rclpy's C typesupport, in ONE process.

Both sides run in the same interpreter, interleaved per round on the same values, so that
machine noise hits both alike and the ratio of medians holds still. That interpreter is the
rclpy oracle's (ROS 2 Jazzy from PyPI, CPython 3.11); run with our venv's python, the bench
re-executes itself there and appends our `src` and our venv's site-packages (cyclonedds,
msgspec, ...) after the oracle's own paths, so rclpy's packages win any name both have.

Per round (order of ours/rclpy alternating), for every row: N calls of one side back to
back, then N of the other; the garbage collector is off inside a batch (as in `timeit`).
Reported: median µs per sample over the rounds, p10–p90, and the ratio of the medians.
Every round checks that both encoders wrote the same bytes.

Usage: .venv/bin/python bench/codec.py [--oracle PY] [--rounds 21] [--quick]
Writes the `## Codec` section of docs/benchmarks.md (not with --quick).
"""

from __future__ import annotations

import argparse
import array
import gc
import math
import os
import platform
import statistics
import struct
import subprocess
import sys
import sysconfig
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, NoReturn

from report import write_section  # bench/report.py (the script's own folder)

ROOT = Path(__file__).resolve().parents[1]
PATHS_ENV = "RCAN_BENCH_OUR_PATHS"  # our src + venv site-packages, handed to the re-exec
TARGET = 1.0

Fn = Callable[[Any], Any]


# -- one process: the oracle's interpreter with our package importable ---------------------
def default_oracle() -> Path:
    env = os.environ.get("RCAN_RTPS_ORACLE_JAZZY")
    return Path(env) if env else ROOT / ".cache/ros-jazzy/bin/python"


def has_rclpy() -> bool:
    try:
        import rclpy.serialization  # noqa: F401
    except ImportError:
        return False
    return True


def reexec(oracle: Path) -> NoReturn:
    """Replaces this process with the oracle's python running this script."""
    if not oracle.exists():
        sys.exit(f"no rclpy oracle at {oracle}: pass --oracle or set RCAN_RTPS_ORACLE_JAZZY")
    version = subprocess.run([str(oracle), "-c", "import sys; print(sys.version_info[:2])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    if version != str(sys.version_info[:2]):  # our C extensions need the same CPython
        sys.exit(f"oracle {oracle} is Python {version}, ours {sys.version_info[:2]}")
    ours = [str(ROOT / "src"), sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]]
    env = {**os.environ, PATHS_ENV: os.pathsep.join(dict.fromkeys(ours))}
    os.execve(str(oracle), [str(oracle), __file__, *sys.argv[1:]], env)


def add_our_paths() -> None:
    default = [ROOT / "src", ROOT / ".venv/lib/python3.11/site-packages"]
    paths = os.environ.get(PATHS_ENV, os.pathsep.join(map(str, default))).split(os.pathsep)
    sys.path.extend(p for p in paths if p not in sys.path)  # after the oracle's: rclpy's win
    sys.path.append(str(ROOT / "tests"))  # oracle.rclpy_agent


# -- the values --------------------------------------------------------------------------
def header(frame: str) -> dict[str, Any]:
    return {"stamp": {"sec": 1_700_000_000, "nanosec": 123_456_789}, "frame_id": frame}


def doubles(n: int, scale: float) -> array.array[float]:
    return array.array("d", (scale * (i + 1) for i in range(n)))


def floats(n: int, scale: float) -> array.array[float]:
    return array.array("f", (scale * (i + 1) for i in range(n)))


def point_cloud() -> dict[str, Any]:
    fields = [{"name": name, "offset": 4 * i, "datatype": 7, "count": 1}  # 7: FLOAT32
              for i, name in enumerate(("x", "y", "z", "intensity"))]
    data = b"".join(struct.pack("<4f", i * 0.1, i * 0.2, i * 0.3, float(i)) for i in range(100))
    return {"header": header("lidar"), "height": 1, "width": 100, "fields": fields,
            "is_bigendian": False, "point_step": 16, "row_step": 1600, "data": data,
            "is_dense": True}


def covariant(kind: str, value: dict[str, Any], scale: float) -> dict[str, Any]:
    return {kind: value, "covariance": doubles(36, scale)}


CASES: dict[str, tuple[str, dict[str, Any]]] = {  # numeric sequences as array.array
    "Twist": ("geometry_msgs/msg/Twist",
              {"linear": {"x": 0.5, "y": 0.1, "z": 0.0},
               "angular": {"x": 0.0, "y": 0.0, "z": 0.25}}),
    "JointState(12)": ("sensor_msgs/msg/JointState",
                       {"header": header("base_link"), "name": [f"joint_{i}" for i in range(12)],
                        "position": doubles(12, 0.1), "velocity": doubles(12, 0.2),
                        "effort": doubles(12, 0.3)}),
    "Odometry": ("nav_msgs/msg/Odometry",
                 {"header": header("odom"), "child_frame_id": "base_link",
                  "pose": covariant("pose", {"position": {"x": 1.0, "y": 2.0},
                                             "orientation": {"z": 0.6, "w": 0.8}}, 0.01),
                  "twist": covariant("twist", {"linear": {"x": 0.5}, "angular": {"z": 0.1}},
                                     0.02)}),
    "Image 640×480 rgb8": ("sensor_msgs/msg/Image",
                           {"header": header("camera"), "height": 480, "width": 640,
                            "encoding": "rgb8", "is_bigendian": 0, "step": 1920,
                            "data": bytes(range(256)) * 3600}),
    "LaserScan(720)": ("sensor_msgs/msg/LaserScan",
                       {"header": header("laser"), "angle_min": -math.pi, "angle_max": math.pi,
                        "angle_increment": 2 * math.pi / 720, "time_increment": 1e-4,
                        "scan_time": 0.1, "range_min": 0.1, "range_max": 30.0,
                        "ranges": floats(720, 0.01), "intensities": floats(720, 1.0)}),
    "PointCloud2(100)": ("sensor_msgs/msg/PointCloud2", point_cloud()),
}


def as_lists(value: Any) -> Any:
    """The same values as JSON would give them: array.array → list (bytes stay bytes)."""
    if isinstance(value, Mapping):
        return {k: as_lists(v) for k, v in value.items()}
    if isinstance(value, (array.array, list)):
        return [as_lists(v) for v in value]
    return value


def has_arrays(value: Any) -> bool:
    if isinstance(value, Mapping):
        return any(has_arrays(v) for v in value.values())
    return isinstance(value, array.array)


def put_arrays(message: Any, values: Mapping[str, Any]) -> Any:
    """Sets the array.array values of `values` onto a typed message (nested fields too)."""
    for name, value in values.items():
        if isinstance(value, array.array):
            setattr(message, name, value)
        elif isinstance(value, Mapping):
            put_arrays(getattr(message, name), value)
    return message


# -- the two sides -----------------------------------------------------------------------
@dataclass(frozen=True)
class Side:
    """One codec's calls for one type, resolved once, outside the timed loops."""

    encode: Fn  # typed message → bytes
    encode_plain: Fn  # plain dict → bytes
    decode: Fn  # bytes → typed message
    decode_plain: Fn  # bytes → plain values
    typed: Fn  # values (array.array kept) → a typed message, built untimed


def ours(type_name: str) -> Side:
    """Our public API. The one place to plug in faster entry points as they land."""
    from rcan_rtps.ros.serialization import default_codec

    codec = default_codec()
    encode = partial(codec.serialize, type_name)
    decode = partial(codec.deserialize, type_name)

    def typed(values: Mapping[str, Any]) -> Any:
        return put_arrays(decode(encode(as_lists(values))), values)

    return Side(encode, encode, decode, partial(codec.deserialize, type_name, plain=True), typed)


def rclpy_side(type_name: str) -> tuple[Side, str]:
    """rclpy, plus a note saying how its plain values are made."""
    from oracle.rclpy_agent import fill, load_type
    from rclpy.serialization import deserialize_message, serialize_message

    cls = load_type(type_name)
    decode = partial(deserialize_message, message_type=cls)
    try:
        from rosidl_runtime_py import message_to_ordereddict, set_message_fields
    except ImportError:  # not in the PyPI oracle: the agent's fill, and rclpy_plain below
        build: Fn = lambda values: fill(cls(), values)  # noqa: E731
        to_plain: Fn = rclpy_plain
        note = ("rosidl_runtime_py is not in the oracle: plain encode = tests/oracle/rclpy_agent "
                "`fill` (setattr per field through rclpy's checking setters) + "
                "`serialize_message`; plain decode = `deserialize_message` + a walk of "
                "`get_fields_and_field_types` (arrays via `tolist()`, bytes via `list()`), "
                "standing in for `message_to_ordereddict`")
    else:
        def build(values: Any) -> Any:
            message = cls()
            set_message_fields(message, values)
            return message

        to_plain = message_to_ordereddict
        note = ("plain encode = `rosidl_runtime_py.set_message_fields` + `serialize_message`; "
                "plain decode = `deserialize_message` + `message_to_ordereddict`")
    side = Side(serialize_message, lambda values: serialize_message(build(values)), decode,
                lambda data: to_plain(decode(data)), lambda values: fill(cls(), values))
    return side, note


def rclpy_plain(value: Any) -> Any:
    if hasattr(value, "get_fields_and_field_types"):
        return {name: rclpy_plain(getattr(value, name))
                for name in value.get_fields_and_field_types()}
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if hasattr(value, "tolist"):  # array.array, numpy arrays: converted in C
        return value.tolist()
    if isinstance(value, list):
        return [rclpy_plain(v) for v in value]
    return value


# -- rows and timing ---------------------------------------------------------------------
@dataclass
class Row:
    message: str
    direction: str
    variant: str
    ours: tuple[Fn, Any]
    theirs: tuple[Fn, Any]
    target: bool  # the ≤ 1.0× target applies to this row
    n: int = 1
    ours_us: list[float] = field(default_factory=list)
    theirs_us: list[float] = field(default_factory=list)
    mismatch: bool = False  # the sides' bytes mean different values (any round)
    padding: int = 0  # most padding bytes that differed in a round (values equal)


def rows_of(label: str, type_name: str, values: dict[str, Any]) -> list[Row]:
    mine, (theirs, _) = ours(type_name), rclpy_side(type_name)
    plain = as_lists(values)
    data = mine.encode(plain)
    typed = "typed, array input" if has_arrays(values) else "typed"
    rows = [Row(label, "encode", typed, (mine.encode, mine.typed(values)),
                (theirs.encode, theirs.typed(values)), True)]
    if has_arrays(values):
        rows.append(Row(label, "encode", "typed, list input", (mine.encode, mine.typed(plain)),
                        (theirs.encode, theirs.typed(plain)), False))
    # both sides decode our bytes: rclpy must read them as it reads its own (float32 rounded)
    own = theirs.decode(theirs.encode(theirs.typed(values)))
    misread = theirs.decode(data) != own
    rows += [Row(label, "encode", "plain", (mine.encode_plain, plain),
                 (theirs.encode_plain, plain), True),
             Row(label, "decode", "typed", (mine.decode, data), (theirs.decode, data), True,
                 mismatch=misread),
             Row(label, "decode", "plain", (mine.decode_plain, data),
                 (theirs.decode_plain, data), True)]
    return rows


def batch(call: tuple[Fn, Any], n: int) -> tuple[float, Any]:
    """µs per call over `n` calls back to back, and the last call's result."""
    fn, arg = call
    gc.disable()
    try:
        t0 = time.perf_counter()
        for _ in range(n):
            out = fn(arg)
        elapsed = time.perf_counter() - t0
    finally:
        gc.enable()
    return elapsed / n * 1e6, out


def per_call_s(call: tuple[Fn, Any]) -> float:
    """A warm estimate: first calls (lazy set-up, cold caches) would make N far too small."""
    batch(call, 3)
    n = 1
    while (us := batch(call, n)[0]) * n < 2_000:  # at least 2 ms of calls
        n *= 2
    return us / 1e6


def calibrate(row: Row, budget_s: float) -> None:
    """N so that the slower side's batch takes about `budget_s`; the same N for both."""
    slower = max(per_call_s(row.ours), per_call_s(row.theirs))
    row.n = max(1, min(20_000, int(budget_s / slower)))


def reencoder(side: Side) -> Fn:
    return lambda data: side.encode(side.decode(data))


def padding_diff(mine: bytes, theirs: bytes, reencode: Fn) -> int | None:
    """How many bytes differ, if only where CDR pads for alignment (rclpy leaves padding
    uninitialised): then ours re-encodes rclpy's bytes into ours exactly. None: values differ."""
    if mine == theirs:
        return 0
    if len(mine) == len(theirs) and reencode(theirs) == mine:
        return sum(a != b for a, b in zip(mine, theirs, strict=True))
    return None


def run_round(rows: list[Row], reencoders: dict[str, Fn], ours_first: bool) -> None:
    for row in rows:
        sides = [(row.ours, row.ours_us), (row.theirs, row.theirs_us)]
        outs = []
        for call, sink in sides if ours_first else sides[::-1]:
            us, out = batch(call, row.n)
            sink.append(us)
            outs.append(out)
        if row.direction == "encode":
            mine, theirs = outs if ours_first else outs[::-1]
            diff = padding_diff(bytes(mine), bytes(theirs), reencoders[row.message])
            if diff is None:
                row.mismatch = True
                print(f"WIRE MISMATCH: {row.message} {row.variant}", file=sys.stderr)
            row.padding = max(row.padding, diff or 0)
    gc.collect()


def measure(rounds: int, budget_s: float) -> list[Row]:
    rows: list[Row] = []
    reencoders: dict[str, Fn] = {}
    for label, (type_name, values) in CASES.items():
        rows += rows_of(label, type_name, values)
        reencoders[label] = reencoder(ours(type_name))
    for row in rows:
        calibrate(row, budget_s)
    for r in range(rounds):
        run_round(rows, reencoders, ours_first=r % 2 == 0)
    return rows


# -- the report --------------------------------------------------------------------------
def us(value: float) -> str:
    return f"{value:.2f}" if value < 10 else f"{value:.1f}" if value < 1000 else f"{value:,.0f}"


def spread(samples: list[float]) -> str:
    deciles = statistics.quantiles(samples, n=10, method="inclusive")
    return f"{us(statistics.median(samples))} ({us(deciles[0])}–{us(deciles[-1])})"


def table_row(row: Row) -> str:
    ratio = statistics.median(row.ours_us) / statistics.median(row.theirs_us)
    verdict = ("met" if ratio <= TARGET else "**not met**") if row.target else "—"
    return (f"| {row.message} | {row.direction} | {row.variant} | {spread(row.ours_us)} | "
            f"{spread(row.theirs_us)} | {ratio:.2f}× | {verdict} |")


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [ln.split(":", 1)[1].strip() for ln in cpuinfo.read_text().splitlines()
                 if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    return (f"{cpu}, {os.cpu_count()} cores shared with other work, {platform.system()} "
            f"{platform.release()}, CPython {platform.python_version()}")


def commit() -> str:
    done = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                          capture_output=True, text=True, check=False)
    return done.stdout.strip() or "unknown"


def report(rows: list[Row], rounds: int, budget_ms: float, note: str) -> str:
    bad = [f"{r.message} {r.direction} {r.variant}" for r in rows if r.mismatch]
    padded: dict[str, int] = {}
    for row in rows:
        if row.padding:
            padded[row.message] = max(padded.get(row.message, 0), row.padding)
    pads = ", ".join(f"{m} {n}" for m, n in padded.items())
    lines = [
        "## Codec", "",
        f"`bench/codec.py` at {commit()}: ours and rclpy (Jazzy, C typesupport) in one "
        f"process, {rounds} rounds, each round timing a batch of N calls of each side back to "
        "back, the order alternating per round (N per row: the slower side's batch takes "
        f"about {budget_ms:g} ms). Cells: median µs per sample over the rounds (p10–p90). "
        f"Ratio = ours / rclpy medians; lower is better. Machine: {machine()}.", "",
        "| message | direction | variant | ours µs | rclpy µs | ratio | target ≤ 1.0× |",
        "|---|---|---|---|---|---|---|",
        *(table_row(r) for r in rows), "",
        "What each cell measures (the same values on both sides; decode rows decode the same "
        "bytes):",
        "- encode typed: ours `rcan_rtps.ros.serialize(type, msg)` on a typed message "
        "(array input: numeric sequences are `array.array`; list input: Python lists); rclpy "
        "`serialize_message(msg)` (its messages hold `array.array`/numpy whatever the input, "
        "so both typed rows time the same rclpy call).",
        "- encode plain: ours `serialize(type, dict)` (values validated field by field, lists "
        f"for numeric sequences, bytes for `uint8[]`); rclpy: {note}.",
        "- decode typed: ours `deserialize(type, data)`; rclpy `deserialize_message(data, cls)`.",
        "- decode plain: ours `deserialize(type, data, plain=True)`; rclpy: see above.",
        "- Target ≤ 1.0× applies to every row but encode typed with list input (the target is "
        "for array input).",
        "- Wire check: every round, both encoders' bytes compared; once, rclpy decodes our "
        "bytes and compares with what it decodes from its own. "
        + (f"**Values differ: {', '.join(bad)}.** " if bad else "Same values everywhere. ")
        + ("Bytes differ only in CDR alignment padding, which rclpy's serializer does not "
           f"zero (most bytes differing in a round: {pads}); ours re-encodes rclpy's bytes "
           "to ours exactly." if pads else "Bytes identical."),
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--oracle", type=Path, default=default_oracle())
    parser.add_argument("--rounds", type=int, default=21)
    parser.add_argument("--budget-ms", type=float, default=50.0,
                        help="target length of the slower side's batch")
    parser.add_argument("--quick", action="store_true",
                        help="5 rounds, short batches, docs untouched: a smoke run")
    args = parser.parse_args()
    if not has_rclpy():
        reexec(args.oracle)
    add_our_paths()
    rounds, budget = (5, 0.003) if args.quick else (args.rounds, args.budget_ms / 1e3)
    started = time.perf_counter()
    rows = measure(rounds, budget)
    text = report(rows, rounds, budget * 1e3, rclpy_side(CASES["Twist"][0])[1])
    print(text)
    print(f"({time.perf_counter() - started:.0f} s)", file=sys.stderr)
    if not args.quick:
        write_section("## Codec", text)
    return 1 if any(r.mismatch for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
