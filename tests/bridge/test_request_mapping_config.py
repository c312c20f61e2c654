"""`bridge.ros2.request_mapping[s]`: the service/action mapping is overridable in config."""

from __future__ import annotations

from pathlib import Path

import pytest

from rcan_rtps.bridge.runtime import nav_mapping
from rcan_rtps.config import ConfigError, loads_config
from rcan_rtps.ros.services import RequestMapping

BASE = """\
robot: {{ruri: rcan://registry.local/acme/rover/unit-0001}}
bridge:
  ros2:
    nav_action: navigate_to_pose
{extra}
  api: {{auth_token_env: RCAN_BRIDGE_TOKEN}}
  safety: {{max_linear_vel: 1.0, max_angular_vel: 1.0}}
"""
ENV = {"RCAN_BRIDGE_TOKEN": "t" * 32}


def config(extra: str) -> object:
    return loads_config(BASE.format(extra=extra), env=ENV)


def test_default_is_auto() -> None:
    assert nav_mapping(config("")) is RequestMapping.AUTO  # type: ignore[arg-type]


def test_global_and_per_name_overrides(tmp_path: Path) -> None:
    assert nav_mapping(config("    request_mapping: fastdds")) is RequestMapping.FASTDDS  # type: ignore[arg-type]
    both = config("    request_mapping: fastdds\n"
                  "    request_mappings: {navigate_to_pose: cyclone}")
    assert nav_mapping(both) is RequestMapping.CYCLONE  # type: ignore[arg-type]


def test_a_bad_mapping_is_named_with_its_line() -> None:
    with pytest.raises(ConfigError) as err:
        config("    request_mapping: zenoh")
    assert "request_mapping" in str(err.value) and "line 5" in str(err.value)


def test_each_goal_route_takes_its_own_servers_override() -> None:
    from rcan_rtps.bridge.goals import route_mapping

    ros2 = config("    request_mapping: fastdds\n"
                  "    request_mappings: {dock_robot: cyclone}").bridge.ros2  # type: ignore[attr-defined]
    assert route_mapping(ros2, "dock_action") is RequestMapping.CYCLONE
    assert route_mapping(ros2, "nav_action") is RequestMapping.FASTDDS
