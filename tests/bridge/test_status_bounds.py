"""What STATUS copies from the robot's nodes is bounded, and a bound never reads as fine
(bridge/faults.py, bridge/joints.py: no DDS)."""

from __future__ import annotations

import msgspec

from rcan_rtps.bridge.faults import (
    MAX_MESSAGE,
    MAX_NAME,
    UNLISTED,
    FaultTable,
    component_name,
)
from rcan_rtps.bridge.joints import MAX_JOINTS, bounded_joints


def listed(table: FaultTable) -> dict[str, str]:
    return {f.name: f.level for f in table.faults()}


def test_a_flood_of_components_is_bounded_and_counted() -> None:
    """88,000 unique names made a 4.7 MB STATUS: the table keeps its cap, and one ERROR
    says how many are not listed."""
    table = FaultTable(max_faults=256)
    for i in range(4_000):
        table.report(f"flood/{i}", "WARN", "x" * 100)
    faults = table.faults()
    assert len(faults) == 257
    assert faults[-1].name == UNLISTED and faults[-1].level == "ERROR"
    assert faults[-1].message.startswith("3744 more")
    assert len(msgspec.json.encode(faults)) < 64_000


def test_an_error_takes_the_place_of_a_warning_never_the_reverse() -> None:
    table = FaultTable(max_faults=3)
    for name in ("a", "b", "c"):
        table.report(name, "WARN", "warm")
    table.report("motor", "ERROR", "overheat")
    assert listed(table)["motor"] == "ERROR"
    assert sum(level == "WARN" for level in listed(table).values()) == 2
    table.report("arm", "ERROR", "stall")
    table.report("wheel", "ERROR", "stall")
    table.report("late", "WARN", "warm")  # no room, and it does not evict an ERROR
    table.report("later", "STALE", "quiet")
    assert {n for n, level in listed(table).items() if level == "ERROR"} == {
        "motor", "arm", "wheel", UNLISTED}
    assert "5 more" in table.faults()[-1].message  # a, b, c, late, later


def test_an_error_beyond_a_table_of_errors_is_counted_not_lost() -> None:
    table = FaultTable(max_faults=2)
    table.report("a", "ERROR", "1")
    table.report("b", "ERROR", "2")
    table.report("c", "ERROR", "3")
    assert [f.name for f in table.faults()] == ["a", "b", UNLISTED]


def test_what_was_not_listed_clears_when_it_reports_ok_or_returns_when_there_is_room() -> None:
    table = FaultTable(max_faults=2)
    table.report("a", "ERROR", "1")
    table.report("b", "ERROR", "2")
    table.report("c", "ERROR", "3")
    table.report("d", "WARN", "4")
    table.report("a", None, "ok")  # room again
    table.report("c", "ERROR", "3 again")  # listed now
    assert [f.name for f in table.faults()] == ["b", "c", UNLISTED]
    table.report("d", None, "ok")
    assert [f.name for f in table.faults()] == ["b", "c"]


def test_past_what_is_followed_the_count_stays() -> None:
    """Names of unlisted components are themselves bounded; past that nobody can say when
    they clear, so the ERROR stays (fail closed)."""
    table = FaultTable(max_faults=1, max_unlisted=2)
    for name in "abcd":
        table.report(name, "ERROR", "x")
    for name in "abcd":
        table.report(name, None, "ok")
    assert [f.name for f in table.faults()] == [UNLISTED]
    assert "until the bridge restarts" in table.faults()[0].message


def test_names_and_messages_are_cut() -> None:
    table = FaultTable()
    table.report("n" * 10_000, "ERROR", "m" * 1_000_000)
    table.report("n" * 10_000 + "2", "ERROR", "other")  # same first characters: not merged
    faults = table.faults()
    assert len(faults) == 2
    assert all(len(f.name) <= MAX_NAME and len(f.message) <= MAX_MESSAGE for f in faults)
    assert "+999" in faults[0].message or "+999" in faults[1].message
    assert component_name("motor") == "motor"


def test_a_huge_joint_state_is_cut_to_its_bound_with_its_count() -> None:
    n = 100_000
    joints = bounded_joints([f"j{i}" for i in range(n)], [float(i) for i in range(n)], [])
    assert joints.count == n
    assert joints.names == [f"j{i}" for i in range(MAX_JOINTS)]
    assert joints.positions == [float(i) for i in range(MAX_JOINTS)]
    assert joints.velocities == []


def test_the_commanded_joints_are_kept_and_stay_paired() -> None:
    """Cutting never hides the joints the bridge moves, nor pairs a name with another
    joint's position."""
    n = 1000
    names = [f"j{i}" for i in range(n)]
    joints = bounded_joints(names, [float(i) for i in range(n)], [-float(i) for i in range(n)],
                            commanded=frozenset({"j900", "j999"}))
    assert len(joints.names) == MAX_JOINTS and {"j900", "j999"} <= set(joints.names)
    for name, position, velocity in zip(joints.names, joints.positions, joints.velocities,
                                        strict=True):
        assert position == float(name[1:]) and velocity == -position


def test_a_small_joint_state_is_copied_as_it_is() -> None:
    joints = bounded_joints(["elbow", "wrist"], [0.5, 0.25], [0.0, 0.1])
    assert (joints.names, joints.positions, joints.velocities, joints.count) == (
        ["elbow", "wrist"], [0.5, 0.25], [0.0, 0.1], 2)


def test_values_without_names_are_bounded_too() -> None:
    joints = bounded_joints([], [0.0] * 10_000, [0.0] * 10_000)
    assert len(joints.positions) == MAX_JOINTS == len(joints.velocities)
    assert joints.count == 0
