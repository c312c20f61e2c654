"""Encode/decode cost per sample: our cyclonedds-based codec vs rclpy's C typesupport.

Both sides are measured in the same run on the same values; the result table (µs per
sample and our/rclpy ratio) replaces the `## Codec` section of docs/benchmarks.md.
Usage: .venv/bin/python bench/codec.py [--oracle .cache/ros-jazzy/bin/python]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from report import write_section  # bench/report.py (the script's own folder)

from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.values import MessageValues

ROOT = Path(__file__).resolve().parents[1]
JOINTS = [f"joint_{i}" for i in range(12)]
CASES: dict[str, tuple[str, dict[str, Any]]] = {
    "Twist": ("geometry_msgs/msg/Twist",
              {"linear": {"x": 0.5}, "angular": {"z": 0.25}}),
    "JointState(12)": ("sensor_msgs/msg/JointState",
                       {"name": JOINTS, "position": [0.1] * 12, "velocity": [0.2] * 12,
                        "effort": [0.3] * 12}),
    "Odometry": ("nav_msgs/msg/Odometry",
                 {"header": {"frame_id": "odom"}, "child_frame_id": "base_link",
                  "pose": {"covariance": [0.01] * 36}, "twist": {"covariance": [0.02] * 36}}),
    "Image 640x480 rgb8": ("sensor_msgs/msg/Image",
                           {"height": 480, "width": 640, "encoding": "rgb8", "step": 1920,
                            "data": list(bytes(640 * 480 * 3))}),
}

RCLPY_SIDE = r"""
import json, sys, time, importlib
from rclpy.serialization import serialize_message, deserialize_message
sys.path.insert(0, sys.argv[1])
from oracle.rclpy_agent import fill, load_type
cases = json.loads(sys.stdin.read())
out = {}
for label, (type_name, value, n) in cases.items():
    cls = load_type(type_name)
    msg = fill(cls(), value)
    t0 = time.perf_counter()
    for _ in range(n):
        data = serialize_message(msg)
    t1 = time.perf_counter()
    for _ in range(n):
        deserialize_message(data, cls)
    t2 = time.perf_counter()
    out[label] = [(t1 - t0) / n * 1e6, (t2 - t1) / n * 1e6]
print(json.dumps(out))
"""


def iterations(label: str) -> int:
    return 50 if label.startswith("Image") else 5000


def ours() -> dict[str, tuple[float, float]]:
    values = MessageValues(DdsTypes(TypeStore(distro="jazzy")))
    results = {}
    for label, (type_name, value) in CASES.items():
        msg = values.build(type_name, value)
        cls = type(msg)
        n = iterations(label)
        t0 = time.perf_counter()
        for _ in range(n):
            data = msg.serialize()
        t1 = time.perf_counter()
        for _ in range(n):
            cls.deserialize(data)
        t2 = time.perf_counter()
        results[label] = ((t1 - t0) / n * 1e6, (t2 - t1) / n * 1e6)
    return results


def theirs(oracle: Path) -> dict[str, tuple[float, float]]:
    payload = {label: [t, v, iterations(label)] for label, (t, v) in CASES.items()}
    done = subprocess.run([str(oracle), "-c", RCLPY_SIDE, str(ROOT / "tests")],
                          input=json.dumps(payload), capture_output=True, text=True, check=True)
    return {k: (v[0], v[1]) for k, v in json.loads(done.stdout).items()}


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--oracle", type=Path, default=ROOT / ".cache/ros-jazzy/bin/python")
    args = parser.parse_args()
    a, b = ours(), theirs(args.oracle)
    rows = ["## Codec", "",
            "`bench/codec.py`: µs per sample, same machine, same run, same values. "
            "Ratio = ours / rclpy (C typesupport); lower is better.", "",
            "| message | encode ours | encode rclpy | ratio | decode ours | decode rclpy | ratio |",
            "|---|---|---|---|---|---|---|"]
    for label in CASES:
        (eo, do), (er, dr) = a[label], b[label]
        rows.append(f"| {label} | {eo:.1f} | {er:.1f} | {eo / er:.1f}× | {do:.1f} | {dr:.1f} | "
                    f"{do / dr:.1f}× |")
    rows.append("")
    write_section("## Codec", "\n".join(rows))
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
