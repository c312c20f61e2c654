"""Regenerates tests/data/cdr_vectors.json: CDR bytes of fixed values, made by real rclpy.

Run from the repository root with the product's interpreter; it drives the ROS 2 Jazzy
oracle's interpreter as a subprocess (no node, no DDS traffic: only
`rclpy.serialization.serialize_message` / `deserialize_message`):

    .venv/bin/python tests/data/make_cdr_vectors.py [--oracle .cache/ros-jazzy/bin/python]

For each case rclpy fills a message from the values, serializes it and reads it back; the
stored `values` are what rclpy read back (every field, defaults included). Fast CDR leaves
alignment padding uninitialised and may return a buffer longer than the message, so the
stored `hex` is rclpy's bytes with the padding bytes set to zero and the tail cut at the
message end. Padding positions come from the test-only reference encoder
(tests/ros/cdr_reference.py); everything outside padding must already equal rclpy's bytes
or the script fails, and rclpy must decode the stored bytes back to the stored values.

The tests (tests/ros/test_cdr_vectors.py) only read the JSON file; they never need ROS.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
OUT = HERE / "cdr_vectors.json"
TEST_IDL = HERE / "idl"

UUID = list(range(0x10, 0x20))
STAMP = {"sec": 1_700_000_123, "nanosec": 456_789_000}
POSE = {
    "position": {"x": 1.25, "y": -2.5, "z": 0.125},
    "orientation": {"x": 0.0, "y": 0.0, "z": 0.7071067811865476, "w": 0.7071067811865476},
}

# (name of the vector, ROS type, values given to rclpy). Every float32 value is exactly
# representable, so values compare exactly after a round trip through the wire.
CASES: list[tuple[str, str, dict[str, Any]]] = [
    (
        "twist",
        "geometry_msgs/msg/Twist",
        {"linear": {"x": 0.5, "y": 0.0, "z": -1.0}, "angular": {"x": 0.0, "y": 0.1, "z": -0.3}},
    ),
    ("header", "std_msgs/msg/Header", {"stamp": STAMP, "frame_id": "base_link"}),
    ("header_empty_frame", "std_msgs/msg/Header", {"stamp": {"sec": -1, "nanosec": 1}}),
    ("string_utf8", "std_msgs/msg/String", {"data": "héllo ✓ wörld"}),
    ("empty", "std_msgs/msg/Empty", {}),
    ("uint64_max", "std_msgs/msg/UInt64", {"data": 2**64 - 1}),
    ("int8_min", "std_msgs/msg/Int8", {"data": -128}),
    (
        "joint_state",
        "sensor_msgs/msg/JointState",
        {
            "header": {"stamp": STAMP, "frame_id": "arm"},
            "name": ["shoulder", "elbow", "w"],
            "position": [0.1, -1.5, 3.0],
            "velocity": [0.0, 0.25, -0.25],
            "effort": [],
        },
    ),
    (
        "image_small",
        "sensor_msgs/msg/Image",
        {
            "header": {"stamp": STAMP, "frame_id": "camera"},
            "height": 2,
            "width": 2,
            "encoding": "rgb8",
            "is_bigendian": 0,
            "step": 6,
            "data": [0, 1, 2, 3, 4, 5, 250, 251, 252, 253, 254, 255],
        },
    ),
    (
        "odometry",
        "nav_msgs/msg/Odometry",
        {
            "header": {"stamp": STAMP, "frame_id": "odom"},
            "child_frame_id": "base_link",
            "pose": {"pose": POSE, "covariance": [i * 0.5 for i in range(36)]},
            "twist": {
                "twist": {"linear": {"x": 0.5}, "angular": {"z": -0.25}},
                "covariance": [(-1.0) ** i * i for i in range(36)],
            },
        },
    ),
    (
        "basic_types",
        "test_msgs/msg/BasicTypes",
        {
            "bool_value": True,
            "byte_value": 0xAB,
            "char_value": 0x7A,
            "float32_value": -1.125,
            "float64_value": 3.141592653589793,
            "int8_value": -7,
            "uint8_value": 200,
            "int16_value": -12345,
            "uint16_value": 54321,
            "int32_value": -123456789,
            "uint32_value": 4_000_000_000,
            "int64_value": -(2**62) - 3,
            "uint64_value": 2**64 - 2,
        },
    ),
    (
        "bounded_strings",
        "test_msgs/msg/Strings",
        {
            "string_value": "unbounded",
            "bounded_string_value": "exactly22characters!!!",
            "bounded_string_value_default3": "",
        },
    ),
    (
        "battery_state",
        "sensor_msgs/msg/BatteryState",
        {
            "header": {"stamp": STAMP, "frame_id": "battery"},
            "voltage": 24.5,
            "temperature": 31.25,
            "current": -1.5,
            "charge": 3.75,
            "capacity": 5.0,
            "design_capacity": 5.5,
            "percentage": 0.75,
            "power_supply_status": 2,
            "power_supply_health": 1,
            "power_supply_technology": 3,
            "present": True,
            "cell_voltage": [4.0, 4.125, 3.875],
            "cell_temperature": [30.5, 31.0, 30.75],
            "location": "bay1",
            "serial_number": "SN-001",
        },
    ),
    (
        "nav_sat_fix",
        "sensor_msgs/msg/NavSatFix",
        {
            "header": {"stamp": STAMP, "frame_id": "gps"},
            "status": {"status": -1, "service": 1},
            "latitude": 48.8584,
            "longitude": 2.2945,
            "altitude": 35.0,
            "position_covariance": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 4.0],
            "position_covariance_type": 2,
        },
    ),
    (
        "polygon_stamped",
        "geometry_msgs/msg/PolygonStamped",
        {
            "header": {"stamp": STAMP, "frame_id": "map"},
            "polygon": {
                "points": [
                    {"x": 0.0, "y": 0.0, "z": 0.0},
                    {"x": 1.5, "y": 0.0, "z": 0.0},
                    {"x": 1.5, "y": -2.25, "z": 0.5},
                ]
            },
        },
    ),
    (
        "joint_trajectory",
        "trajectory_msgs/msg/JointTrajectory",
        {
            "header": {"stamp": STAMP, "frame_id": ""},
            "joint_names": ["j1", "j2"],
            "points": [
                {
                    "positions": [0.0, 1.0],
                    "velocities": [0.5, 0.5],
                    "accelerations": [],
                    "effort": [],
                    "time_from_start": {"sec": 1, "nanosec": 500_000_000},
                },
                {
                    "positions": [1.0, 2.0],
                    "velocities": [],
                    "accelerations": [0.25, -0.25],
                    "effort": [10.0],
                    "time_from_start": {"sec": 3, "nanosec": 0},
                },
            ],
        },
    ),
    (
        "diagnostic_array",
        "diagnostic_msgs/msg/DiagnosticArray",
        {
            "header": {"stamp": STAMP, "frame_id": ""},
            "status": [
                {
                    "level": 1,
                    "name": "motor",
                    "message": "warm",
                    "hardware_id": "m1",
                    "values": [{"key": "temp", "value": "71"}, {"key": "rpm", "value": "900"}],
                },
                {"level": 0, "name": "bus", "message": "", "hardware_id": "", "values": []},
            ],
        },
    ),
    (
        "participant_entities_info",
        "rmw_dds_common/msg/ParticipantEntitiesInfo",
        {
            "gid": {"data": list(range(16))},
            "node_entities_info_seq": [
                {
                    "node_namespace": "/",
                    "node_name": "rcan_bridge",
                    "reader_gid_seq": [{"data": [1] * 16}],
                    "writer_gid_seq": [{"data": [2] * 16}, {"data": list(range(255, 239, -1))}],
                }
            ],
        },
    ),
    (
        "parameter_descriptor",
        "rcl_interfaces/msg/ParameterDescriptor",
        {
            "name": "max_speed",
            "type": 3,
            "description": "m/s",
            "additional_constraints": "",
            "read_only": False,
            "dynamic_typing": True,
            "floating_point_range": [{"from_value": 0.0, "to_value": 2.5, "step": 0.5}],
            "integer_range": [],
        },
    ),
    (
        "goal_status_array",
        "action_msgs/msg/GoalStatusArray",
        {
            "status_list": [
                {"goal_info": {"goal_id": {"uuid": UUID}, "stamp": STAMP}, "status": 2},
                {
                    "goal_info": {
                        "goal_id": {"uuid": [0xFF] * 16},
                        "stamp": {"sec": 0, "nanosec": 0},
                    },
                    "status": 6,
                },
            ]
        },
    ),
    ("set_bool_request", "std_srvs/srv/SetBool_Request", {"data": True}),
    (
        "set_bool_response",
        "std_srvs/srv/SetBool_Response",
        {"success": False, "message": "motors are off"},
    ),
    (
        "get_plan_request",
        "nav_msgs/srv/GetPlan_Request",
        {
            "start": {"header": {"stamp": STAMP, "frame_id": "map"}, "pose": POSE},
            "goal": {
                "header": {"stamp": STAMP, "frame_id": "map"},
                "pose": {"position": {"x": 5.0, "y": 5.0}},
            },
            "tolerance": 0.25,
        },
    ),
    (
        "set_parameters_request",
        "rcl_interfaces/srv/SetParameters_Request",
        {
            "parameters": [
                {"name": "use_sim_time", "value": {"type": 1, "bool_value": True}},
                {"name": "gains", "value": {"type": 8, "double_array_value": [0.5, 1.5]}},
                {"name": "blob", "value": {"type": 5, "byte_array_value": [0, 127, 255]}},
                {"name": "ids", "value": {"type": 7, "integer_array_value": [-1, 2**40]}},
                {"name": "names", "value": {"type": 9, "string_array_value": ["a", "bc", ""]}},
            ]
        },
    ),
    (
        "cancel_goal_request",
        "action_msgs/srv/CancelGoal_Request",
        {"goal_info": {"goal_id": {"uuid": UUID}, "stamp": {"sec": 0, "nanosec": 0}}},
    ),
    (
        "fibonacci_send_goal_request",
        "test_msgs/action/Fibonacci_SendGoal_Request",
        {"goal_id": {"uuid": UUID}, "goal": {"order": 10}},
    ),
    (
        "fibonacci_send_goal_response",
        "test_msgs/action/Fibonacci_SendGoal_Response",
        {"accepted": True, "stamp": STAMP},
    ),
    (
        "fibonacci_get_result_response",
        "test_msgs/action/Fibonacci_GetResult_Response",
        {"status": 4, "result": {"sequence": [0, 1, 1, 2, 3, 5, 8]}},
    ),
    (
        "fibonacci_feedback_message",
        "test_msgs/action/Fibonacci_FeedbackMessage",
        {"goal_id": {"uuid": UUID}, "feedback": {"sequence": [0, 1, 1]}},
    ),
]


def _worker() -> None:
    """Runs under the oracle's interpreter: JSON requests on stdin, JSON answers on stdout."""
    sys.path.insert(0, str(ROOT / "tests" / "oracle"))
    from rclpy.serialization import deserialize_message, serialize_message
    from rclpy_agent import fill, load_type, plain

    answers = []
    for req in json.load(sys.stdin):
        cls = load_type(req["type"])
        if "hex" in req:
            answers.append({"values": plain(deserialize_message(bytes.fromhex(req["hex"]), cls))})
        else:
            msg = fill(cls(), req["values"])
            answers.append({"hex": serialize_message(msg).hex(), "values": plain(msg)})
    json.dump(answers, sys.stdout)


def _ask(oracle: Path, requests: list[dict[str, Any]]) -> list[dict[str, Any]]:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    done = subprocess.run(
        [str(oracle), __file__, "--worker"],
        input=json.dumps(requests),
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    if done.returncode:
        raise SystemExit(f"oracle failed:\n{done.stderr[-3000:]}")
    answers: list[dict[str, Any]] = json.loads(done.stdout)
    return answers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    default = os.environ.get("RCAN_RTPS_ORACLE_JAZZY") or ROOT / ".cache/ros-jazzy/bin/python"
    parser.add_argument("--oracle", type=Path, default=Path(default))
    args = parser.parse_args()

    sys.path.insert(0, str(ROOT / "tests"))
    from ros.cdr_reference import encode, equal_ignoring_padding

    from rcan_rtps.ros.typesys.store import TypeStore

    store = TypeStore([TEST_IDL], distro="jazzy")
    first = _ask(args.oracle, [{"type": t, "values": v} for _, t, v in CASES])
    vectors: list[dict[str, Any]] = []
    for (name, type_name, _), answer in zip(CASES, first, strict=True):
        theirs = bytes.fromhex(answer["hex"])
        header, body = theirs[:4], theirs[4:]
        if header != bytes([0, 1, 0, 0]):
            raise SystemExit(f"{name}: unexpected encapsulation {header.hex()}")
        reference, padding = encode(store, type_name, answer["values"])
        if not equal_ignoring_padding(reference, body[: len(reference)], padding):
            raise SystemExit(f"{name}: rclpy's bytes differ from the reference outside padding")
        canonical = header + bytes(0 if pad else b for b, pad in zip(body, padding, strict=False))
        entry: dict[str, Any] = {
            "name": name,
            "type": type_name,
            "hex": canonical.hex(),
            "values": answer["values"],
        }
        if canonical != theirs:
            entry["rclpy_hex"] = theirs.hex()  # as rclpy returned it: padding, trailing bytes
        vectors.append(entry)
    second = _ask(args.oracle, [{"type": v["type"], "hex": v["hex"]} for v in vectors])
    for vector, answer in zip(vectors, second, strict=True):
        if answer["values"] != vector["values"]:
            raise SystemExit(f"{vector['name']}: rclpy does not decode the stored bytes back")
    doc = {
        "_generated_by": "tests/data/make_cdr_vectors.py (see tests/data/README.md)",
        "_oracle": "ROS 2 Jazzy rclpy from PyPI, rmw_fastrtps_cpp, serialize_message",
        "vectors": vectors,
    }
    OUT.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
    print(f"wrote {len(vectors)} vectors to {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    if sys.argv[1:] == ["--worker"]:
        _worker()
    else:
        main()
