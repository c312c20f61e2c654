"""The generated `ros2msg` definitions against the official `.msg` files of ROS 2 Jazzy."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from rcan_rtps.ros.typesys.msgdef import DELIMITER, full_definition, msg_text
from rcan_rtps.ros.typesys.store import TypeStore

_BUILTIN = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
            "int32", "uint32", "int64", "uint64", "string", "wstring"}


def _value(text: str) -> object:
    text = text.strip()
    if text[:1] in ("'", '"'):  # 'a"b' and "a\"b" spell the same string
        return ast.literal_eval(text)
    try:
        return float(text)
    except ValueError:
        return text.lower()


def meaning(text: str, package: str) -> tuple[list[tuple[str, str, object]], set[tuple[str, str]]]:
    """(fields in order, constants as a set), comments and spelling differences removed:
    package-relative names made absolute, `char` as `uint8` (rosidl's IDL form)."""
    fields, constants = [], set()
    for raw in text.splitlines():
        line = raw.split("#")[0].strip()
        if not line:
            continue
        kind, rest = line.split(None, 1)
        base = re.match(r"[\w/]+", kind).group(0)  # type: ignore[union-attr]
        if "/" not in base and base not in _BUILTIN:
            kind = kind.replace(base, f"{package}/{base}", 1)
        if base == "char":
            kind = kind.replace("char", "uint8", 1)
        if "=" in rest and not rest.split("=")[0].strip().count(" "):
            name, value = (p.strip() for p in rest.split("=", 1))
            constants.add((f"{kind} {name}", str(_value(value))))
            continue
        name, _, default = rest.partition(" ")
        fields.append((kind, name, _value(default) if default.strip() else None))
    return fields, constants


def test_every_bundled_message_matches_its_official_msg_file(jazzy_share: Path) -> None:
    store = TypeStore()
    compared = 0
    for name in store.interface_names():
        package, kind, short = name.split("/")
        official = jazzy_share / package / "msg" / f"{short}.msg"
        if kind != "msg" or not official.is_file():
            continue
        ours = msg_text(store.message(name))
        assert meaning(ours, package) == meaning(official.read_text(), package), name
        compared += 1
    assert compared > 100


def test_dependencies_follow_in_rosbag2_order() -> None:
    text = full_definition("geometry_msgs/msg/PoseStamped", TypeStore().message)
    heads = re.findall(rf"^{DELIMITER}\nMSG: (\S+)$", text, flags=re.M)
    # depth first, siblings by name, each once
    assert heads == ["geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion",
                     "std_msgs/Header", "builtin_interfaces/Time"]
    assert text.startswith("std_msgs/Header header\nPose pose\n\n" + DELIMITER)


@pytest.mark.offline
def test_empty_struct_has_an_empty_definition() -> None:
    assert msg_text(TypeStore().message("std_msgs/msg/Empty")) == "\n"
