"""The simulated robot's parameters on the wire (`ros2 param list /robot1/sim_robot`): the
`use_sim_time` every ROS 2 node declares, and its own rates and limits from `SimParams`.
Limits and power figures can be changed while it runs; what fixes the robot's build or its
loop (rates, wheel geometry, battery size) is read-only."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

from ..ros.parameters import Parameter, ParameterServer
from .robot import SimParams, SimRobot

DESCRIPTIONS = {
    "rate_hz": "odometry and physics rate (Hz)",
    "cmd_timeout_s": "stop when no cmd_vel arrived for this long (s)",
    "wheel_radius_m": "wheel radius (m)",
    "wheel_base_m": "distance between the wheels (m)",
    "max_linear": "the sim's own linear speed limit (m/s), above any governed limit",
    "max_angular": "the sim's own angular speed limit (rad/s)",
    "battery_wh": "battery capacity (Wh)",
    "idle_w": "power drawn standing still (W)",
    "drive_w_per_mps": "power drawn per m/s of speed (W)",
    "charge_w": "power the dock supplies (W)",
}
READ_ONLY = frozenset({"rate_hz", "wheel_radius_m", "wheel_base_m", "battery_wh"})


def _positive(value: Any) -> str | None:
    return None if value > 0 else "must be greater than 0"


def _not_negative(value: Any) -> str | None:
    return None if value >= 0 else "must not be negative"


def _wall_clock_only(value: Any) -> str | None:
    return "the simulated robot keeps wall-clock time (it has no /clock)" if value else None


def sim_parameters(robot: SimRobot) -> list[Parameter]:
    params = [Parameter("use_sim_time", False, "use the /clock topic for time",
                        check=_wall_clock_only)]
    for field in fields(SimParams):
        params.append(Parameter(
            field.name, float(getattr(robot.params, field.name)), DESCRIPTIONS[field.name],
            read_only=field.name in READ_ONLY,
            check=_positive if field.name == "cmd_timeout_s" else _not_negative))
    return params


def serve_parameters(robot: SimRobot) -> ParameterServer:
    """The robot's parameter services on its node; an accepted set applies at once."""
    def apply(name: str, value: Any) -> None:
        if name in DESCRIPTIONS:
            setattr(robot.params, name, float(value))

    return ParameterServer(robot.node, sim_parameters(robot), on_set=apply)
