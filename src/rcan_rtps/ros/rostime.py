"""ROS time and geometry values (builtin_interfaces Time/Duration, planar quaternions)."""

from __future__ import annotations

import math
import time
from typing import Any


def now_msg() -> dict[str, int]:
    """`builtin_interfaces/Time` for the wall clock now (diff_drive drops stale stamps)."""
    ns = time.time_ns()
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def duration_msg(seconds: float) -> dict[str, int]:
    # Rounded once, as a whole: rounding the fraction alone sent 0.9999999999 s as 0 s.
    sec, nanosec = divmod(round(seconds * 1e9), 1_000_000_000)
    return {"sec": sec, "nanosec": nanosec}


def yaw_to_quaternion(yaw: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2.0), "w": math.cos(yaw / 2.0)}


def quaternion_to_yaw(q: Any) -> float:
    """Yaw (rotation about z) of a quaternion with fields x, y, z, w."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
