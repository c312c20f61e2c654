"""RIHS01 hashes of the IDL bundle equal the official ROS 2 Jazzy ones, with no ROS around.

The expected values are copied from the type description files ROS 2 Jazzy ships
(tests/data/rihs01_jazzy.json, made by tests/data/make_rihs01_vectors.py), computed by the
official generator from the official files of the packages not on PyPI
(tests/data/rihs01_official_jazzy.json, made by tests/data/make_rihs01_official.py), plus the
nav2_msgs hashes pinned from a Jazzy install (tests/data/rihs01_nav2_jazzy.json). Our hashes
are computed from `idl/` (and tests/data/idl/, fixed test_msgs input) by the product's hasher.
"""

from __future__ import annotations

import pytest

from rcan_rtps.ros.typesys.hashing import rihs01, type_id
from rcan_rtps.ros.typesys.model import Collection, FieldType, Primitive
from rcan_rtps.ros.typesys.store import TypeStore

from .offline_data import TEST_IDL, load

pytestmark = pytest.mark.offline

JAZZY: dict[str, str] = load("rihs01_jazzy.json")["hashes"]
OFFICIAL: dict[str, str] = load("rihs01_official_jazzy.json")["hashes"]
NAV2: dict[str, str] = load("rihs01_nav2_jazzy.json")["hashes"]
VECTORS = {**JAZZY, **OFFICIAL, **NAV2}


@pytest.fixture(scope="module")
def store() -> TypeStore:
    return TypeStore([TEST_IDL], distro="jazzy")


def test_vector_files_cover_what_the_bundle_ships(store: TypeStore) -> None:
    packages = {name.split("/")[0] for name in VECTORS}
    for pkg in (
        "std_msgs",
        "geometry_msgs",
        "sensor_msgs",
        "nav_msgs",
        "trajectory_msgs",
        "diagnostic_msgs",
        "action_msgs",
        "unique_identifier_msgs",
        "nav2_msgs",
        "std_srvs",
        "rmw_dds_common",
        "test_msgs",
        "visualization_msgs",
        "shape_msgs",
        "stereo_msgs",
        "actionlib_msgs",
        "tf2_msgs",
        "control_msgs",
        "example_interfaces",
        "vision_msgs",
        "ackermann_msgs",
        "geographic_msgs",
        "statistics_msgs",
    ):
        assert pkg in packages, pkg
    kinds = {name.split("/")[1] for name in VECTORS}
    assert kinds == {"msg", "srv", "action"}
    assert any(name.endswith("_Event") for name in VECTORS)
    assert any(name.endswith("_SendGoal_Request") for name in VECTORS)
    assert len(JAZZY) > 250
    assert len(OFFICIAL) > 500
    # every bundle interface has a vector: official files on PyPI, official generator elsewhere
    bundle = TypeStore(distro="jazzy").interface_names()
    assert [n for n in bundle if n not in JAZZY and n not in OFFICIAL] == []
    assert all(NAV2[n] == OFFICIAL[n] for n in NAV2)


@pytest.mark.parametrize("type_name", sorted(VECTORS))
def test_hash_equals_official(store: TypeStore, type_name: str) -> None:
    assert store.hash_of(type_name) == VECTORS[type_name]


@pytest.mark.parametrize(
    ("type_name", "prefix"),
    [
        # the check values written down in the wire notes, independently of the data files,
        # and TFMessage as `ros2 topic info -v /tf` reports it on a Jazzy graph
        ("std_msgs/msg/String", "RIHS01_df668c74"),
        ("rmw_dds_common/msg/ParticipantEntitiesInfo", "RIHS01_91a0593b"),
        ("nav2_msgs/action/NavigateToPose_SendGoal_Request", "RIHS01_e9381f2a"),
        ("tf2_msgs/msg/TFMessage", "RIHS01_e369d0f0"),
    ],
)
def test_known_prefixes(store: TypeStore, type_name: str, prefix: str) -> None:
    assert store.hash_of(type_name).startswith(prefix)
    assert VECTORS[type_name].startswith(prefix)


def test_distro_override_changes_the_hash() -> None:
    """Humble's Gid is char[24]: a different type description, hence a different hash."""
    jazzy = TypeStore(distro="jazzy").hash_of("rmw_dds_common/msg/Gid")
    humble = TypeStore(distro="humble").hash_of("rmw_dds_common/msg/Gid")
    assert jazzy == VECTORS["rmw_dds_common/msg/Gid"]
    assert humble != jazzy


def test_hash_depends_on_field_names_types_and_order(store: TypeStore) -> None:
    twist = store.message("geometry_msgs/msg/Twist")
    official = VECTORS["geometry_msgs/msg/Twist"]
    assert rihs01(twist, store.message) == official
    swapped = type(twist)(twist.name, tuple(reversed(twist.fields)))
    assert rihs01(swapped, store.message) != official
    renamed = type(twist)(
        twist.name, (twist.fields[0], type(twist.fields[1])("angularr", twist.fields[1].type))
    )
    assert rihs01(renamed, store.message) != official


@pytest.mark.parametrize(
    ("ftype", "expected"),
    [
        # the field type ids of type_description_interfaces/msg/FieldType
        (FieldType(nested="a/msg/B"), 1),
        (FieldType(Primitive.INT8), 2),
        (FieldType(Primitive.UINT64), 9),
        (FieldType(Primitive.FLOAT), 10),
        (FieldType(Primitive.DOUBLE), 11),
        (FieldType(Primitive.BOOLEAN), 15),
        (FieldType(Primitive.OCTET), 16),
        (FieldType(Primitive.STRING), 17),
        (FieldType(Primitive.STRING, string_bound=10), 21),
        (FieldType(Primitive.DOUBLE, collection=Collection.ARRAY, size=36), 11 + 48),
        (FieldType(Primitive.UINT8, collection=Collection.BOUNDED_SEQUENCE, size=3), 3 + 96),
        (FieldType(Primitive.STRING, collection=Collection.SEQUENCE), 17 + 144),
        (FieldType(nested="a/msg/B", collection=Collection.SEQUENCE), 1 + 144),
        (FieldType(Primitive.STRING, None, 5, Collection.BOUNDED_SEQUENCE, 4), 21 + 96),
    ],
)
def test_field_type_ids(ftype: FieldType, expected: int) -> None:
    assert type_id(ftype) == expected
