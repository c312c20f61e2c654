"""What the wire layer keeps after a start, and what it lets go of (issue 27: idle footprint).

A topic's XTypes description is cyclonedds' Python objects only until Cyclone's C side has
copied its bytes; the type store looks its files up rather than holding an index of all.
Each check is of behaviour (what is held, what is found, that peers still match), not of a
memory figure."""

from __future__ import annotations

import asyncio
import gc
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cyclonedds.idl._typesupport.DDS import XTypes
from cyclonedds.idl._xt_builder import XTBuilder
from cyclonedds.qos import Qos
from waiting import eventually

from rcan_rtps.ros import _cyclone_header as cyclone
from rcan_rtps.ros import graph as graph_mod
from rcan_rtps.ros.actions import ActionClient
from rcan_rtps.ros.errors import UnknownTypeError
from rcan_rtps.ros.graph import Direction, Endpoint, RosGraph
from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.qos import Durability, History, QosProfile
from rcan_rtps.ros.typesys.ddstypes import _forget_machines
from rcan_rtps.ros.typesys.store import TypeStore

TWIST = "geometry_msgs/msg/Twist"
ODOM = "nav_msgs/msg/Odometry"
NAV = "nav2_msgs/action/NavigateToPose"


@pytest.fixture
def nodes(domain_id: int) -> Iterator[tuple[RosNode, RosNode]]:
    with RosNode("idle_a", "/idle", domain_id=domain_id, localhost=True) as a, \
            RosNode("idle_b", "/idle", domain_id=domain_id, localhost=True) as b:
        yield a, b


def test_a_topic_keeps_no_xtypes_objects_after_it_is_made(
        nodes: tuple[RosNode, RosNode]) -> None:
    node, _ = nodes
    XTBuilder._type_hash_db.clear()  # filled by a test's topic made with cyclonedds alone
    node.topic("rt/idle/odom", ODOM)  # nested types: Header, Pose…, Twist…
    struct = node.types.struct(ODOM)
    assert struct.__idl__._xt_data == (None, None)
    assert struct.__idl__._xt_bytedata == (None, None)
    assert XTBuilder._type_hash_db == {}


def _xtypes_serializers() -> list[str]:
    """cyclonedds' XTypes classes whose serializer machines are built."""
    return [name for name, cls in vars(XTypes).items()
            if isinstance(cls, type) and getattr(cls, "__idl__", None) is not None
            and getattr(cls.__idl__, "v1_machine", None) is not None]


def test_making_topics_builds_no_serializer_of_cyclonedds_xtypes_classes(
        nodes: tuple[RosNode, RosNode]) -> None:
    """Topics are described by `xtypes.describe`: cyclonedds' describer, which builds the
    serializers of some eighty of its own classes once per program and keeps them, never
    runs; a plain topic and one with the Cyclone request header alike."""
    node, _ = nodes
    for name in _xtypes_serializers():  # built by another test of this process
        _forget_machines(getattr(XTypes, name))
    node.topic("rt/idle/odom", ODOM)
    cyclone.wrapper_topic(node, "rq/idle/cancelRequest", "action_msgs/srv/CancelGoal_Request")
    assert _xtypes_serializers() == []


def test_a_topic_keeps_no_cyclonedds_serializer_of_its_types(
        nodes: tuple[RosNode, RosNode]) -> None:
    """Nor the serializer machines of the type and the types in it, but for
    ros_discovery_info's: cyclonedds' typed readers take it (graph.py, handshake.py), and a
    service call must not wait for a rebuild."""
    node, _ = nodes
    node.topic("rt/idle/odom", ODOM)
    made = {name: node.types.struct(name) for name in (
        ODOM, "std_msgs/msg/Header", "builtin_interfaces/msg/Time",
        "geometry_msgs/msg/PoseWithCovariance", "geometry_msgs/msg/Vector3",
        "rmw_dds_common/msg/ParticipantEntitiesInfo", "rmw_dds_common/msg/Gid")}
    kept = [name for name, cls in made.items() if cls.__idl__.v1_machine is not None]
    assert kept == ["rmw_dds_common/msg/ParticipantEntitiesInfo", "rmw_dds_common/msg/Gid"]


def test_cyclonedds_own_codec_is_rebuilt_the_same_when_asked_for(
        nodes: tuple[RosNode, RosNode]) -> None:
    """raw_cdr.py's and readers.py's public-API fallbacks use cyclonedds' codec: rebuilt on
    demand, it writes the generated codec's bytes; a type whose byte sequences use the
    one-copy bytes codec keeps its adjusted serializer (bytes in, bytes out)."""
    node, _ = nodes
    node.topic("rt/idle/odom", ODOM)
    message = node.values.build(ODOM, {"child_frame_id": "base",
                                       "pose": {"pose": {"position": {"x": 1.5}}}})
    assert message.serialize() == node.codecs.of(ODOM).encode(message)
    image = "sensor_msgs/msg/Image"
    node.topic("rt/idle/image", image)
    assert node.types.struct(image).__idl__.v1_machine is not None
    frame = node.values.build(image, {"height": 1, "width": 3, "encoding": "mono8",
                                      "step": 3, "data": b"abc"})
    data = frame.serialize()
    assert data == node.codecs.of(image).encode(frame)
    assert type(frame).deserialize(data).data == b"abc"


async def test_peers_match_after_the_description_was_let_go_of(
        nodes: tuple[RosNode, RosNode]) -> None:
    """The second node describes the type again (the first one's objects are gone): the same
    bytes, so Cyclone matches them and a message goes through."""
    a, b = nodes
    pub = a.create_publisher("/idle/odom", ODOM)
    sub = b.create_subscription("/idle/odom", ODOM)
    await eventually(lambda: pub.matched_count() == 1 and sub.matched_count() == 1,
                     timeout=10.0, what="the two nodes' Odometry endpoints to match")
    pub.publish({"child_frame_id": "base", "twist": {"twist": {"linear": {"x": 0.5}}}})
    got = await asyncio.wait_for(sub.get(), 10.0)
    assert got.child_frame_id == "base"
    assert got.twist.twist.linear.x == 0.5


def _package(root: Path, pkg: str, kind: str, name: str, text: str) -> None:
    (root / pkg / kind).mkdir(parents=True, exist_ok=True)
    (root / pkg / kind / f"{name}.idl").write_text(text)


IDL = """module {pkg} {{ module msg {{ struct {name} {{ {field}; }}; }}; }};"""


def test_the_store_finds_a_file_added_after_its_first_lookup(tmp_path: Path) -> None:
    """No index is held: a lookup looks at the paths as they are (an index made by the first
    lookup missed files added later)."""
    _package(tmp_path, "idle_pkg", "msg", "First", IDL.format(
        pkg="idle_pkg", name="First", field="int32 a"))
    store = TypeStore([tmp_path], include_bundle=False)
    assert [f.name for f in store.message("idle_pkg/msg/First").fields] == ["a"]
    _package(tmp_path, "idle_pkg", "msg", "Later", IDL.format(
        pkg="idle_pkg", name="Later", field="double b"))
    assert [f.name for f in store.message("idle_pkg/msg/Later").fields] == ["b"]
    assert store.interface_names() == ["idle_pkg/msg/First", "idle_pkg/msg/Later"]


def test_the_first_path_holding_a_type_wins_and_odd_names_are_not_found(
        tmp_path: Path) -> None:
    first, second = tmp_path / "first", tmp_path / "second"
    _package(first, "idle_pkg", "msg", "T", IDL.format(pkg="idle_pkg", name="T", field="int8 x"))
    _package(second, "idle_pkg", "msg", "T", IDL.format(pkg="idle_pkg", name="T",
                                                        field="int8 y"))
    _package(second, "_hidden", "msg", "T", IDL.format(pkg="_hidden", name="T", field="int8 z"))
    store = TypeStore([first, second], include_bundle=False)
    assert [f.name for f in store.message("idle_pkg/msg/T").fields] == ["x"]
    assert store.source_of("idle_pkg/msg/T") == first / "idle_pkg" / "msg" / "T.idl"
    for name in ("_hidden/msg/T", "idle_pkg/msg/.T", "idle_pkg/nope/T", "idle_pkg/msg/T/x"):
        with pytest.raises(Exception, match="T"):
            store.source_of(name)
    # a root that is itself one package
    single = TypeStore([first / "idle_pkg"], include_bundle=False)
    assert single.source_of("idle_pkg/msg/T") == first / "idle_pkg" / "msg" / "T.idl"
    assert single.interface_names() == ["idle_pkg/msg/T"]


async def test_the_graph_keeps_each_endpoint_as_its_ros_view_with_shared_profiles(
        nodes: tuple[RosNode, RosNode]) -> None:
    """A discovered endpoint is kept as what the views show of it, not as its builtin sample
    (a `Qos` of policy objects, ~2 kB each, for every endpoint of the domain): the peer's
    endpoints are described as before, and endpoints of equal QoS share one profile."""
    a, b = nodes
    keep_all = QosProfile(history=History.KEEP_ALL, durability=Durability.TRANSIENT_LOCAL)
    b.create_publisher("/idle/one", TWIST, keep_all)
    b.create_publisher("/idle/two", TWIST, keep_all)
    b.create_subscription("/idle/three", ODOM)
    graph = RosGraph(a)

    def seen() -> list[Endpoint]:
        graph.refresh()
        return [e for e in graph.endpoints()
                if e.ros_name in ("/idle/one", "/idle/two", "/idle/three")]

    await eventually(lambda: len(seen()) == 3, timeout=10.0, what="b's three endpoints")
    one, three, two = sorted(seen(), key=lambda e: e.ros_name)
    assert (one.ros_name, one.ros_type, one.direction) == ("/idle/one", TWIST,
                                                           Direction.PUBLISHER)
    assert (three.ros_type, three.direction) == (ODOM, Direction.SUBSCRIPTION)
    assert one.qos == two.qos == keep_all.with_(depth=one.qos.depth)
    assert one.qos is two.qos  # one object per distinct profile
    assert (three.qos.history, three.qos.depth) == (History.KEEP_LAST, 10)
    assert one.type_hash == a.store.hash_of(TWIST)
    assert one.dds_type == "geometry_msgs::msg::dds_::Twist_"
    assert not any(isinstance(held, Qos) for held in gc.get_referents(*graph._endpoints.values()))


async def _churn(graph: RosGraph, peer: RosNode, qos_of: Callable[[int], QosProfile]) -> None:
    """`peer` makes twelve publishers (/idle/churn0..11, `qos_of(n)` each), one at a time,
    each seen by `graph` before it is deleted, and the last seen gone."""
    def seen(name: str) -> bool:
        graph.refresh()
        return any(e.ros_name == name for e in graph.endpoints())

    for n in range(12):
        writer = peer.create_publisher(f"/idle/churn{n}", TWIST, qos_of(n))
        await eventually(lambda n=n: seen(f"/idle/churn{n}"), timeout=10.0, what=f"churn{n}")
        writer.close()
    await eventually(lambda: not seen("/idle/churn11"), timeout=10.0, what="churn gone")


async def test_topic_and_type_names_are_shared_but_never_interned(
        nodes: tuple[RosNode, RosNode], monkeypatch: pytest.MonkeyPatch) -> None:
    """Endpoints of one topic share its name and type name, one object each; but any peer
    chooses them, and CPython 3.12.0-3.12.5 never frees an interned string (cpython#113993):
    `sys.intern` of ever new names was memory a churning peer took for good. They are kept
    by the graph's own table, which lets go of names no endpoint (nor a recent departure)
    names once it doubled."""
    monkeypatch.setattr(graph_mod, "TEXTS_KEPT", 8, raising=False)
    monkeypatch.setattr(graph_mod, "DEPARTURES_BOUND", 2, raising=False)  # (nor kept as
    monkeypatch.setattr(graph_mod, "DEPARTURES_KEPT_S", 0.0, raising=False)  # departures)
    a, b = nodes
    graph = RosGraph(a)
    b.create_publisher("/idle/named", TWIST)
    b.create_subscription("/idle/named", TWIST)
    await _churn(graph, b, lambda n: QosProfile())
    in_use = set(graph._texts_in_use())
    assert len(graph._texts) <= max(8, 2 * len(in_use))
    churned = [f"rt/idle/churn{n}" for n in range(12)]
    assert len([name for name in churned if name in graph._texts._kept]) < 12
    pub, sub = sorted((s for s in graph._endpoints.values() if s.topic_name == "rt/idle/named"),
                      key=lambda s: s.direction.value)
    assert pub.topic_name is sub.topic_name and pub.type_name is sub.type_name
    # (interned, the table's own object would come back for an equal string made anew)
    fresh = "".join(["rt/idle/", "named"])
    assert sys.intern(fresh) is not pub.topic_name


async def test_profiles_no_endpoint_uses_are_let_go_of(
        nodes: tuple[RosNode, RosNode], monkeypatch: pytest.MonkeyPatch) -> None:
    """A peer making endpoints of ever new QoS (here a history depth each) and deleting them does
    not grow the graph's shared profiles for good; the profile an endpoint still uses is kept
    and still shared."""
    monkeypatch.setattr(graph_mod, "PROFILES_KEPT", 4, raising=False)
    a, b = nodes
    graph = RosGraph(a)
    kept = QosProfile(depth=99)
    b.create_publisher("/idle/kept", TWIST, kept)
    await _churn(graph, b, lambda n: QosProfile(depth=100 + n))
    assert len(graph._profiles) <= 2 * 4, graph._profiles
    b.create_publisher("/idle/kept2", TWIST, kept)

    def both() -> list[Endpoint]:
        graph.refresh()
        return [e for e in graph.endpoints() if e.ros_name in ("/idle/kept", "/idle/kept2")]

    await eventually(lambda: len(both()) == 2, timeout=10.0, what="both kept endpoints")
    first, second = both()
    assert first.qos is second.qos and first.qos.depth == 99


async def test_an_action_client_parses_its_action_at_its_first_use(
        nodes: tuple[RosNode, RosNode]) -> None:
    """A bridge's goal clients only cancel until their first goal: the action's own
    definition (goal, result, feedback and the types derived from them) is parsed then, not
    when the client is made; an unknown action still fails when it is made."""
    node, _ = nodes
    client = ActionClient(node, "navigate_to_pose", NAV)
    try:
        assert not [n for n in node.store._types if n.startswith(NAV)]
        assert client.types.goal.name == NAV + "_Goal"
        assert NAV + "_SendGoal_Request" in node.store._types
    finally:
        client.close()
    with pytest.raises(UnknownTypeError, match="NavigateToPoze"):
        ActionClient(node, "navigate_to_pose", "nav2_msgs/action/NavigateToPoze")


async def test_bag_plays_look_at_the_graph_lets_go_of_it(
        nodes: tuple[RosNode, RosNode]) -> None:
    """`bag play` looks at the graph once before playing (`_await_matches`). A graph's
    ros_discovery_info reader is watched by the node's reader thread, which takes each info
    into the graph's inbox: left open, that watch (its reader, its inbox of up to 12 MiB) stayed
    for the whole playback, the collector never freeing it as it did the graph's other readers."""
    from rcan_rtps.cli.bag_cmd import _await_matches

    node, _ = nodes
    await _await_matches(node, {})
    assert [w.label for w in node.reader_thread._watches
            if w.label.startswith("ros_discovery_info")] == []
