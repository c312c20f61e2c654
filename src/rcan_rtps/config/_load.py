"""Load `.rcan.yaml` into RcanConfig, reporting every problem with its key path and YAML line."""

from __future__ import annotations

import io
import os
import urllib.parse
from collections.abc import Mapping
from pathlib import Path

import msgspec
import msgspec.inspect
import yaml

from ._errors import ConfigError, ConfigIssue
from ._model import AUDIT_SIDECARS, PrincipalConfig, RcanConfig, estop_state_file
from ._schema import (
    INT_TAG,
    INVALID,
    MAP_TAG,
    STR_TAG,
    Walker,
    Where,
    is_null,
    key_text,
    line_of,
    mapping_pairs,
)

_SCHEMA = msgspec.inspect.type_info(RcanConfig)
# Far above any real config (the largest example is 5 KB): what is larger is no config, and
# reading it whole (a huge file, /dev/zero) could take minutes or all the memory there is.
MAX_CONFIG_BYTES = 1024 * 1024


def load_config(
    path: str | os.PathLike[str], *, env: Mapping[str, str] | None = None
) -> RcanConfig:
    """Read and validate a config file; raises ConfigError listing every issue found."""
    source = str(path)
    try:
        with open(path, "rb") as file:
            data = file.read(MAX_CONFIG_BYTES + 1)  # one byte more tells "too large"
    except OSError as exc:
        raise ConfigError(source, [ConfigIssue("$", None, f"cannot read: {exc}")]) from exc
    if len(data) > MAX_CONFIG_BYTES:
        msg = f"more than {MAX_CONFIG_BYTES} bytes: too large to be a config file"
        raise ConfigError(source, [ConfigIssue("$", None, msg)])
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(source, [ConfigIssue("$", None, f"cannot read: {exc}")]) from exc
    config = loads_config(text, source=source, env=env)
    config = _resolve_paths(config, Path(path).resolve().parent)
    issues = shared_file_issues(config, source)
    if issues:
        raise ConfigError(source, issues)
    return config


def loads_config(
    text: str, *, source: str = "<config>", env: Mapping[str, str] | None = None
) -> RcanConfig:
    env = os.environ if env is None else env
    root = _compose(text, source)
    walker = Walker()
    walker.issues.extend(_apply_env_fallbacks(root, env))
    config = walker.value(root, _SCHEMA, Where("$", line_of(root)))
    if walker.issues or config is INVALID:
        issues = sorted(walker.issues, key=lambda i: (i.line or 0, i.path))
        raise ConfigError(source, issues)
    assert isinstance(config, RcanConfig)
    return config


def _compose(text: str, source: str) -> yaml.MappingNode:
    """The document's node tree (nodes keep their lines); values are constructed while walking."""
    try:
        stream = io.StringIO(text)
        stream.name = source  # YAML's messages name the file, not a string
        root = yaml.compose(stream, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise ConfigError(source, [ConfigIssue("$", line, f"not valid YAML: {exc}")]) from exc
    except RecursionError as exc:  # PyYAML composes nested collections recursively
        raise ConfigError(source, [ConfigIssue("$", None, "nested too deeply")]) from exc
    if root is None or is_null(root):
        raise ConfigError(source, [ConfigIssue("$", 1, "the file is empty; expected a mapping")])
    if not isinstance(root, yaml.MappingNode):
        raise ConfigError(
            source, [ConfigIssue("$", line_of(root), "expected a mapping at the top")]
        )
    return root


def _apply_env_fallbacks(root: yaml.MappingNode, env: Mapping[str, str]) -> list[ConfigIssue]:
    """ROS_DOMAIN_ID / ROS_DISTRO fill `bridge.ros2` keys the file leaves out.

    They go in as nodes without a line, so the walk checks them like any other value.
    """
    ros2 = _ros2_node(root)
    present = _entries(ros2)
    if ros2 is None or present is None:
        return []
    issues: list[ConfigIssue] = []
    domain = env.get("ROS_DOMAIN_ID")
    if "domain_id" not in present and domain:
        try:
            _put(ros2, "domain_id", yaml.ScalarNode(INT_TAG, str(int(domain))))
        except ValueError:
            msg = f"ROS_DOMAIN_ID={domain!r} is not an integer"
            issues.append(ConfigIssue("$.bridge.ros2.domain_id", None, msg))
    distro = env.get("ROS_DISTRO")
    if "distro" not in present and distro:
        _put(ros2, "distro", yaml.ScalarNode(STR_TAG, distro))
    return issues


def _ros2_node(root: yaml.MappingNode) -> yaml.MappingNode | None:
    """`bridge.ros2`, added empty if the bridge has none; None unless both are mappings."""
    bridge = (_entries(root) or {}).get("bridge")
    entries = _entries(bridge)
    if not isinstance(bridge, yaml.MappingNode) or entries is None:
        return None
    ros2 = entries.get("ros2")
    if ros2 is None:
        ros2 = yaml.MappingNode(MAP_TAG, [])
        _put(bridge, "ros2", ros2)
    return ros2 if isinstance(ros2, yaml.MappingNode) else None


def _entries(node: yaml.Node | None) -> dict[str, yaml.Node] | None:
    """A mapping node's values by key; None if it is no mapping or its `<<` merge is broken."""
    if not isinstance(node, yaml.MappingNode) or node.tag != MAP_TAG:
        return None
    try:
        return {key_text(key): value for key, value in mapping_pairs(node)}
    except yaml.YAMLError:
        return None  # the walk reports it


def _put(mapping: yaml.MappingNode, key: str, value: yaml.Node) -> None:
    mapping.value.append((yaml.ScalarNode(STR_TAG, key), value))


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
        jwt = msgspec.structs.replace(api.jwt, public_key=rel(api.jwt.public_key),
                                      jwks=rel(api.jwt.jwks))
        api = msgspec.structs.replace(api, jwt=jwt)
    api = msgspec.structs.replace(api, principals=[
        _signer_paths(p, base) for p in api.principals])
    bridge = msgspec.structs.replace(bridge, audit=audit, safety=safety, api=api)
    return msgspec.structs.replace(config, bridge=bridge)


def _signer_paths(principal: PrincipalConfig, base: Path) -> PrincipalConfig:
    if principal.signatures is None:
        return principal
    keys = [key if key.public_key_file is None else
            msgspec.structs.replace(key, public_key_file=str(base / key.public_key_file))
            for key in principal.signatures.keys]
    return msgspec.structs.replace(principal, signatures=msgspec.structs.replace(
        principal.signatures, keys=keys))


def shared_file_issues(config: RcanConfig, source: str) -> list[ConfigIssue]:
    """Files the bridge writes that are one file with another it writes or reads (after
    `..` and links are resolved). `estop_state_path: audit.jsonl` loaded, and the first e-stop
    replaced the audit log with the latch (the running log went on into an unlinked file);
    `path` = `key_path` made the key the log. Files it only reads may be one (a certificate
    that is its own CA)."""
    by_file: dict[object, list[tuple[str, str, bool]]] = {}
    for key, path, written in _bridge_files(config, source):
        by_file.setdefault(_file_identity(path), []).append((key, path, written))
    issues = []
    for names in by_file.values():
        writers = [(key, path) for key, path, written in names if written]
        if len(names) > 1 and writers:
            key, path = writers[0]
            others = ", ".join(other for other, _, _ in names[1:])
            issues.append(ConfigIssue(f"$.{key}", None, f"{path} is also {others}: the bridge "
                                      "writes it, so it must be a file of its own"))
    return issues


def _file_identity(path: str) -> object:
    """What makes two paths one file: the inode of one that is there (a hard link is a second
    name of it, as is a name differing in case on a case-insensitive file system), else the
    path with `..` and links resolved (the file a start would make)."""
    try:
        info = os.stat(path)
    except (OSError, ValueError):
        return os.path.realpath(path)
    return (info.st_dev, info.st_ino)


def _bridge_files(config: RcanConfig, source: str) -> list[tuple[str, str, bool]]:
    """(config key, path, whether the bridge writes it): those it writes first, so that a
    file it only reads is reported at the key of the write that would clobber it."""
    bridge, api = config.bridge, config.bridge.api
    log = bridge.audit.path
    written = [("bridge.audit.path", log), ("bridge.audit.key_path", bridge.audit.key_path),
               ("bridge.safety.estop_state_path", estop_state_file(bridge))]
    written += [(f"bridge.audit.path ({suffix})", log + suffix) for suffix in AUDIT_SIDECARS]
    witness = bridge.audit.witness
    if witness is not None and witness.startswith("file:"):
        parts = urllib.parse.urlsplit(witness)
        written.append(("bridge.audit.witness", urllib.parse.unquote(parts.path)))
    read = [("the config file", source)]
    if api.tls is not None:
        read += [("bridge.api.tls.cert", api.tls.cert), ("bridge.api.tls.key", api.tls.key)]
        if api.tls.client_ca is not None:
            read.append(("bridge.api.tls.client_ca", api.tls.client_ca))
    if api.jwt is not None:
        read.append(("bridge.api.jwt", api.jwt.jwks or api.jwt.public_key or ""))
    return [(k, p, True) for k, p in written] + [(k, p, False) for k, p in read]
