"""Load `.rcan.yaml` into RcanConfig, reporting every problem with its key path and YAML line."""

from __future__ import annotations

import copy
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import msgspec
import yaml

from rcan_rtps.rcan import validation_path

from ._errors import ConfigError, ConfigIssue
from ._model import RcanConfig

_MISSING = re.compile(r"Object missing required field `(?P<field>[^`]+)`")
_UNKNOWN = re.compile(r"Object contains unknown field `(?P<field>[^`]+)`")
_NAMED = re.compile(r"`(?P<field>[A-Za-z_][A-Za-z0-9_]*)`:? ")
_PLAINTEXT_KEYS = ("token", "auth_token", "password", "secret")
_MAX_ROUNDS = 100
# Valid stand-ins for required keys: after reporting a bad or missing one, checking goes on
# with its siblings instead of dropping the whole parent section.
_STANDINS: dict[tuple[str | int, ...], Any] = {
    ("robot",): {"ruri": "rcan://standin/standin/standin/standin0"},
    ("robot", "ruri"): "rcan://standin/standin/standin/standin0",
    ("bridge",): {"api": {"auth_token_env": "STANDIN"},
                  "safety": {"max_linear_vel": 1.0, "max_angular_vel": 1.0}},
    ("bridge", "api"): {"auth_token_env": "STANDIN"},
    ("bridge", "safety"): {"max_linear_vel": 1.0, "max_angular_vel": 1.0},
    ("bridge", "safety", "max_linear_vel"): 1.0,
    ("bridge", "safety", "max_angular_vel"): 1.0,
}
PathKey = tuple[str | int, ...]


def load_config(
    path: str | os.PathLike[str], *, env: Mapping[str, str] | None = None
) -> RcanConfig:
    """Read and validate a config file; raises ConfigError listing every issue found."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(source, [ConfigIssue("$", None, f"cannot read: {exc}")]) from exc
    config = loads_config(text, source=source, env=env)
    return _resolve_paths(config, Path(path).resolve().parent)


def loads_config(
    text: str, *, source: str = "<config>", env: Mapping[str, str] | None = None
) -> RcanConfig:
    env = os.environ if env is None else env
    lines, data = _parse_yaml(text, source)
    issues: list[ConfigIssue] = []
    if not isinstance(data, dict):
        raise ConfigError(source, [ConfigIssue("$", 1, "expected a mapping at the top")])
    _reject_plaintext_secrets(data, (), lines, issues)
    issues.extend(_apply_env_defaults(data, env))
    config = _convert_collecting(data, lines, issues)
    if issues or config is None:
        raise ConfigError(source, sorted(issues, key=lambda i: (i.line or 0, i.path)))
    return config


def _parse_yaml(text: str, source: str) -> tuple[dict[PathKey, int], Any]:
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise ConfigError(source, [ConfigIssue("$", line, f"not valid YAML: {exc}")]) from exc
    lines: dict[PathKey, int] = {}
    if node is not None:
        _map_lines(node, (), lines)
    return lines, data


def _map_lines(node: yaml.Node, at: PathKey, lines: dict[PathKey, int]) -> None:
    lines[at] = node.start_mark.line + 1
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            child = (*at, key.value)
            _map_lines(value, child, lines)
            lines[child] = key.start_mark.line + 1  # point at the key, not its value
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            _map_lines(item, (*at, index), lines)


def _line_of(at: PathKey, lines: dict[PathKey, int]) -> int | None:
    while at not in lines and at:
        at = at[:-1]
    return lines.get(at)


def _dotted(at: PathKey) -> str:
    out = "$"
    for part in at:
        out += f"[{part}]" if isinstance(part, int) else f".{part}"
    return out


def _parse_path(text: str) -> PathKey:
    parts: list[str | int] = []
    for name, index in re.findall(r"\.([^.\[]+)|\[(\d+)\]", text[1:]):
        parts.append(int(index) if index else name)
    return tuple(parts)


def _reject_plaintext_secrets(
    data: Any, at: PathKey, lines: dict[PathKey, int], issues: list[ConfigIssue]
) -> None:
    """A secret in a config file leaks through backups and diffs: only token_env/token_sha256."""
    if isinstance(data, dict):
        for key in list(data):
            if key in _PLAINTEXT_KEYS:
                del data[key]
                where = (*at, key)
                msg = "plaintext secrets are not allowed; use token_env or token_sha256"
                issues.append(ConfigIssue(_dotted(where), _line_of(where, lines), msg))
            else:
                _reject_plaintext_secrets(data[key], (*at, key), lines, issues)
    elif isinstance(data, list):
        for index, item in enumerate(data):
            _reject_plaintext_secrets(item, (*at, index), lines, issues)


def _apply_env_defaults(data: dict[str, Any], env: Mapping[str, str]) -> list[ConfigIssue]:
    bridge = data.get("bridge")
    if not isinstance(bridge, dict):
        return []
    ros2 = bridge.setdefault("ros2", {})
    if not isinstance(ros2, dict):
        return []
    issues: list[ConfigIssue] = []
    if "domain_id" not in ros2 and env.get("ROS_DOMAIN_ID"):
        try:
            ros2["domain_id"] = int(env["ROS_DOMAIN_ID"])
        except ValueError:
            msg = f"ROS_DOMAIN_ID={env['ROS_DOMAIN_ID']!r} is not an integer"
            issues.append(ConfigIssue("$.bridge.ros2.domain_id", None, msg))
    if "distro" not in ros2 and env.get("ROS_DISTRO"):
        ros2["distro"] = env["ROS_DISTRO"]
    return issues


def _convert_collecting(
    data: dict[str, Any], lines: dict[PathKey, int], issues: list[ConfigIssue]
) -> RcanConfig | None:
    """msgspec stops at the first error: record it, drop the bad key, and try again."""
    pruner = _Pruner(data)
    for _ in range(_MAX_ROUNDS):
        try:
            return msgspec.convert(data, RcanConfig)
        except msgspec.ValidationError as exc:
            text, detail = validation_path(exc)
            at, detail = _blame(data, _parse_path(text), detail)
            original = pruner.original(at)
            # An error at or above something already dropped is an echo of that first error.
            if not pruner.caused_by_drop(original):
                issues.append(ConfigIssue(_dotted(original), _line_of(original, lines), detail))
            if not pruner.drop(at):
                return None
    return None


def _blame(data: Any, at: PathKey, detail: str) -> tuple[PathKey, str]:
    """Point at the key an error is about: a missing/unknown field, or a `key` named first."""
    for pattern in (_MISSING, _UNKNOWN):
        match = pattern.match(detail)
        if match is not None:
            return (*at, match["field"]), detail
    match = _NAMED.match(detail)
    if match is not None and match["field"] in (_get(data, at) or {}):
        return (*at, match["field"]), detail[match.end() :].lstrip(": ")
    return at, detail


def _get(data: Any, at: PathKey) -> Any:
    for part in at:
        data = data[part]
    return data


class _Pruner:
    """Deletes bad values while remembering original list indices, so paths stay true."""

    def __init__(self, data: dict[str, Any]) -> None:
        self._data = data
        self._indices: dict[int, list[int]] = {}  # id(list) -> original index per position
        self._dropped: list[PathKey] = []

    def original(self, at: PathKey) -> PathKey:
        node: Any = self._data
        out: list[str | int] = []
        for part in at:
            if isinstance(node, list) and isinstance(part, int):
                out.append(self._index_map(node)[part] if part < len(node) else part)
            else:
                out.append(part)
            node = node[part] if _has(node, part) else None
        return tuple(out)

    def caused_by_drop(self, original: PathKey) -> bool:
        return any(d[: len(original)] == original for d in self._dropped)

    def drop(self, at: PathKey) -> bool:
        """Remove the value at `at` (or, for a missing key, its parent)."""
        while at:
            parent = _get(self._data, at[:-1])
            key = at[-1]
            standin = _STANDINS.get(at)
            if standin is not None and parent.get(key) != standin:
                self._dropped.append(self.original(at))
                parent[key] = copy.deepcopy(standin)
                return True
            if _has(parent, key):
                self._dropped.append(self.original(at))
                if isinstance(parent, list):
                    del self._index_map(parent)[key]  # type: ignore[arg-type]
                del parent[key]
                return True
            at = at[:-1]  # a required key is missing: drop its whole parent
        return False

    def _index_map(self, node: list[Any]) -> list[int]:
        return self._indices.setdefault(id(node), list(range(len(node))))


def _has(node: Any, key: str | int) -> bool:
    if isinstance(node, dict):
        return key in node
    return isinstance(node, list) and isinstance(key, int) and 0 <= key < len(node)


def _resolve_paths(config: RcanConfig, base: Path) -> RcanConfig:
    """Relative file paths in a config mean: relative to the config file."""

    def rel(p: str | None) -> str | None:
        return None if p is None else str(base / p)

    bridge = config.bridge
    audit = msgspec.structs.replace(
        bridge.audit, path=rel(bridge.audit.path), key_path=rel(bridge.audit.key_path)
    )
    safety = msgspec.structs.replace(
        bridge.safety, estop_state_path=rel(bridge.safety.estop_state_path)
    )
    api = bridge.api
    if api.tls is not None:
        tls = msgspec.structs.replace(
            api.tls, cert=rel(api.tls.cert), key=rel(api.tls.key), client_ca=rel(api.tls.client_ca)
        )
        api = msgspec.structs.replace(api, tls=tls)
    if api.jwt is not None:
        api = msgspec.structs.replace(
            api, jwt=msgspec.structs.replace(api.jwt, public_key=rel(api.jwt.public_key))
        )
    bridge = msgspec.structs.replace(bridge, audit=audit, safety=safety, api=api)
    return msgspec.structs.replace(config, bridge=bridge)
