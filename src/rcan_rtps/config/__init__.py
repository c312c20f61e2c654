"""Typed `.rcan.yaml` config.

    load_config(path) -> RcanConfig        raises ConfigError (every issue: key path + YAML line)
    loads_config(text) -> RcanConfig
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from ._errors import ConfigError, ConfigIssue
from ._model import (
    ApiConfig,
    ArmConfig,
    AuditConfig,
    BridgeConfig,
    ConfidenceGate,
    HitlConfig,
    HitlGate,
    ImageFeedConfig,
    JwtConfig,
    MotionConfig,
    MotionLock,
    PrincipalConfig,
    RbacConfig,
    RcanConfig,
    RobotConfig,
    Ros2Config,
    SafetyConfig,
    SecurityConfig,
    SignaturePolicy,
    SignaturesConfig,
    SignerKey,
    SkillConfig,
    TlsConfig,
    estop_state_file,
    issuer_roles,
    plaintext_problem,
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
    "ImageFeedConfig",
    "JwtConfig",
    "MotionConfig",
    "MotionLock",
    "PrincipalConfig",
    "RbacConfig",
    "RcanConfig",
    "RobotConfig",
    "Ros2Config",
    "SafetyConfig",
    "SecurityConfig",
    "SignaturePolicy",
    "SignaturesConfig",
    "SignerKey",
    "SkillConfig",
    "TlsConfig",
    "estop_state_file",
    "issuer_roles",
    "load_config",
    "loads_config",
    "plaintext_problem",
    "polygon_edges",
    "polygon_problem",
]


# The loader (PyYAML, the schema walker) is imported when a config is read, not with the
# package: `rcan-rtps run` releases it once its config is loaded (cli/run_cmd.py).
def load_config(
    path: str | os.PathLike[str], *, env: Mapping[str, str] | None = None
) -> RcanConfig:
    """Read and validate a config file; raises ConfigError listing every issue found."""
    from ._load import load_config as load

    return load(path, env=env)


def loads_config(
    text: str, *, source: str = "<config>", env: Mapping[str, str] | None = None
) -> RcanConfig:
    """Validate a config's text; raises ConfigError listing every issue found."""
    from ._load import loads_config as loads

    return loads(text, source=source, env=env)
