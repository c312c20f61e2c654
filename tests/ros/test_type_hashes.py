"""Every bundle type's RIHS01 hash equals the official one shipped by ROS 2 Jazzy."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rcan_rtps.ros.errors import UnknownTypeError
from rcan_rtps.ros.typesys.store import TypeStore

pytestmark = pytest.mark.interop


def _official_hashes(share: Path, interface: str) -> dict[str, str] | None:
    pkg, kind, name = interface.split("/")
    path = share / pkg / kind / f"{name}.json"
    if not path.exists():
        return None
    doc = json.loads(path.read_text())
    return {h["type_name"]: h["hash_string"] for h in doc["type_hashes"]}


def test_every_bundle_type_hash_matches_jazzy(jazzy_share: Path) -> None:
    store = TypeStore(distro="jazzy")
    compared, missing, wrong = 0, [], []
    for interface in store.interface_names():
        pkg = interface.split("/")[0]
        if not (jazzy_share / pkg).is_dir():
            continue  # not on PyPI: test_official_generator.py hashes the official files
        official = _official_hashes(jazzy_share, interface)
        if official is None:
            missing.append(interface)
            continue
        for type_name, expected in official.items():
            if not type_name.startswith(interface):
                continue  # referenced types are checked through their own file
            compared += 1
            got = store.hash_of(type_name)
            if got != expected:
                wrong.append(f"{type_name}: {got} != {expected}")
    assert not wrong, "\n".join(wrong)
    assert not missing, f"bundle types unknown to the oracle: {missing}"
    assert compared > 100


NAV2_JAZZY = {
    "NavigateToPose_SendGoal_Request":
        "RIHS01_e9381f2acfe9fa8c4838a277d0cde28a93c483564827b9f13496b9c2092e4f09",
    "NavigateToPose_SendGoal_Response":
        "RIHS01_99f97fcbb07daf024df4b8c3f02f19ce7fa3183fcedfb76b8772a61a371a55fa",
    "NavigateToPose_GetResult_Request":
        "RIHS01_106d3457cf0db4c4a8d3373bab3ff6aa8ba8ad99ae6392ce9784830a7d04ac93",
    "NavigateToPose_GetResult_Response":
        "RIHS01_c59f178c377de5318919c00bdbf7884cb3b185acfdffceba6c9f161e0aa3cc81",
    "NavigateToPose_FeedbackMessage":
        "RIHS01_9d1f6fa2eb975ce733b419ac2e97b134d8ff92b6478b6559feed9a50bdfd82b3",
}


@pytest.mark.parametrize("part", sorted(NAV2_JAZZY))
def test_nav2_navigate_to_pose_hashes(part: str) -> None:
    store = TypeStore(distro="jazzy")
    assert store.hash_of(f"nav2_msgs/action/{part}") == NAV2_JAZZY[part]


def test_rosidl_generated_idl_files_load_from_an_extra_path(jazzy_share: Path) -> None:
    """A ROS install's own `share/<pkg>` (test_msgs) loads through --idl-path."""
    store = TypeStore([jazzy_share / "test_msgs"], distro="jazzy")
    checked = 0
    for interface in store.interface_names():
        if not interface.startswith("test_msgs/"):
            continue
        for type_name, expected in (_official_hashes(jazzy_share, interface) or {}).items():
            if type_name.startswith("test_msgs/"):
                assert store.hash_of(type_name) == expected, type_name
                checked += 1
    assert checked >= 30
    fib = store.action("test_msgs/action/Fibonacci")
    assert [f.name for f in fib.send_goal.request.fields] == ["goal_id", "goal"]


def test_unknown_type_suggests_near_names() -> None:
    store = TypeStore(distro="jazzy")
    with pytest.raises(UnknownTypeError) as err:
        store.message("geometry_msgs/msg/Twst")
    assert "geometry_msgs/msg/Twist" in str(err.value)
