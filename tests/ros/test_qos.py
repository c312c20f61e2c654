"""QoS profiles → DDS QoS: what rmw_cyclonedds sets, and the names of incompatible policies."""

from __future__ import annotations

import pytest
from cyclonedds.core import Policy

from rcan_rtps.ros import qos

pytestmark = pytest.mark.offline


def durability_service(profile: qos.QosProfile) -> Policy.DurabilityService | None:
    found = [p for p in profile.to_dds().policies if isinstance(p, Policy.DurabilityService)]
    return found[0] if found else None


def test_transient_local_keeps_the_profiles_history_for_late_joiners() -> None:
    service = durability_service(qos.DEFAULT.with_(
        depth=7, durability=qos.Durability.TRANSIENT_LOCAL))
    assert service is not None and service.history == Policy.History.KeepLast(7)
    keep_all = durability_service(qos.DEFAULT.with_(
        history=qos.History.KEEP_ALL, durability=qos.Durability.TRANSIENT_LOCAL))
    assert keep_all is not None and keep_all.history is Policy.History.KeepAll


def test_volatile_has_no_durability_service() -> None:
    assert durability_service(qos.DEFAULT) is None


def test_policy_names_read_like_rclpy() -> None:
    assert qos.policy_name(11) == "RELIABILITY_QOS_POLICY"
    assert qos.policy_name(2) == "DURABILITY_QOS_POLICY"
    assert qos.policy_name(99) == "UNKNOWN(99)_QOS_POLICY"
