"""Typed `.rcan.yaml` config.

    load_config(path) -> RcanConfig        raises ConfigError (every issue: key path + YAML line)
    loads_config(text) -> RcanConfig
"""

from ._errors import ConfigError, ConfigIssue
from ._load import load_config, loads_config
from ._model import (
    ApiConfig,
    ArmConfig,
    AuditConfig,
    BridgeConfig,
    ConfidenceGate,
    HitlConfig,
    HitlGate,
    JwtConfig,
    MotionConfig,
    MotionLock,
    PrincipalConfig,
    RbacConfig,
    RcanConfig,
    RobotConfig,
    Ros2Config,
    SafetyConfig,
    TlsConfig,
    polygon_edges,
    polygon_problem,
)

__all__ = [
    "ApiConfig",
    "ArmConfig",
    "AuditConfig",
    "BridgeConfig",
    "ConfidenceGate",
    "ConfigError",
    "ConfigIssue",
    "HitlConfig",
    "HitlGate",
    "JwtConfig",
    "MotionConfig",
    "MotionLock",
    "PrincipalConfig",
    "RbacConfig",
    "RcanConfig",
    "RobotConfig",
    "Ros2Config",
    "SafetyConfig",
    "TlsConfig",
    "load_config",
    "loads_config",
    "polygon_edges",
    "polygon_problem",
]
