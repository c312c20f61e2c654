"""Per-distro wire differences: Humble's 24-byte Gid and no type hashes; nav2 results."""

from __future__ import annotations

import pytest

from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.typesys.store import TypeStore, resolve_distro


@pytest.mark.parametrize(("distro", "size"), [("humble", 24), ("jazzy", 16), ("kilted", 16)])
def test_gid_size_follows_the_distro(distro: str, size: int) -> None:
    gid = TypeStore(distro=distro).message("rmw_dds_common/msg/Gid")
    assert gid.fields[0].type.size == size


def test_nav2_result_differs_between_humble_and_jazzy() -> None:
    humble = TypeStore(distro="humble").message("nav2_msgs/action/NavigateToPose_Result")
    jazzy = TypeStore(distro="jazzy").message("nav2_msgs/action/NavigateToPose_Result")
    assert [f.name for f in jazzy.fields] == ["error_code", "error_msg"]
    assert [f.name for f in humble.fields] != [f.name for f in jazzy.fields]


def test_humble_node_announces_24_byte_gids_and_no_type_hash(domain_id: int) -> None:
    with RosNode("old_peer", domain_id=domain_id, distro="humble") as node:
        assert node.gid_size() == 24
        assert node.endpoint_user_data("std_msgs/msg/String") is None
        info = node.values.build("rmw_dds_common/msg/ParticipantEntitiesInfo", {
            "gid": {"data": bytes(24)}, "node_entities_info_seq": []})
        assert len(info.serialize()) == 4 + 24 + 4  # header, gid[24], empty sequence


def test_jazzy_node_tags_endpoints_with_type_hashes(domain_id: int) -> None:
    with RosNode("new_peer", domain_id=domain_id, distro="jazzy") as node:
        data = node.endpoint_user_data("std_msgs/msg/String")
        assert data == f"typehash={node.store.hash_of('std_msgs/msg/String')};".encode()


def test_distro_comes_from_ros_distro(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DISTRO", "humble")
    assert resolve_distro() == "humble"
    monkeypatch.delenv("ROS_DISTRO")
    assert resolve_distro() == "jazzy"
    with pytest.raises(ValueError, match="unsupported ROS distro"):
        resolve_distro("rolling")
