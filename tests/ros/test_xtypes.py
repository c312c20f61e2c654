"""Our XTypes descriptions against cyclonedds' own (issue 27: idle footprint).

`xtypes.describe` writes, from the type model, the TypeInformation and TypeMapping bytes that
Cyclone copies when a topic is made and announces to peers; cyclonedds' `XTBuilder` is the
reference: for every struct type of the bundled IDL (messages, services' requests, responses
and events, actions' derived types), and every service type with rmw_cyclonedds' request
header, the bytes must be the same, so peers see what they saw before.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from cyclonedds.idl import IdlStruct
from cyclonedds.idl._xt_builder import XTBuilder

from rcan_rtps.ros import _cyclone_header as cyclone
from rcan_rtps.ros.errors import UnsupportedTypeError
from rcan_rtps.ros.typesys.ddstypes import DdsTypes
from rcan_rtps.ros.typesys.model import Collection, Field, FieldType, MessageType, Primitive
from rcan_rtps.ros.typesys.store import TypeStore
from rcan_rtps.ros.typesys.xtypes import describe


def cyclonedds_description(cls: type[IdlStruct]) -> tuple[bytes, bytes]:
    """What cyclonedds' own describer makes of `cls` (its `__idl__` left as it was)."""
    idl = cls.__idl__
    idl._xt_data = idl._xt_bytedata = (None, None)  # type: ignore[attr-defined]
    try:
        idl.fill_type_data()
        return idl._xt_bytedata  # type: ignore[attr-defined,no-any-return]
    finally:
        idl._xt_data = idl._xt_bytedata = (None, None)  # type: ignore[attr-defined]
        XTBuilder._type_hash_db.clear()


def struct_names(store: TypeStore) -> Iterator[str]:
    """Every struct type the store's IDL defines or derives."""
    for name in store.interface_names():
        kind = name.split("/")[1]
        if kind == "msg":
            yield name
        elif kind == "srv":
            service = store.service(name)
            yield from (m.name for m in (service.request, service.response, service.event))
        elif kind == "action":
            action = store.action(name)
            yield from (m.name for m in (action.goal, action.result, action.feedback,
                                         action.feedback_message))
            for service in (action.send_goal, action.get_result):
                yield from (m.name for m in (service.request, service.response))


@pytest.mark.parametrize("distro", ["humble", "jazzy", "kilted"])
def test_every_bundled_type_is_described_as_cyclonedds_describes_it(distro: str) -> None:
    store = TypeStore(distro=distro)
    types = DdsTypes(store)
    names = list(struct_names(store))
    assert len(names) > 500  # the whole bundle, not a handful
    differ = [name for name in names
              if describe(store.message(name), store.message)
              != cyclonedds_description(types.struct(name))]
    assert differ == []


def test_service_types_with_the_request_header_too() -> None:
    store = TypeStore()
    types = DdsTypes(store)
    services = [store.service(n) for n in store.interface_names() if "/srv/" in n]
    services += [s for n in store.interface_names() if "/action/" in n
                 for s in (store.action(n).send_goal, store.action(n).get_result)]
    differ = []
    for msg in (m for service in services for m in (service.request, service.response)):
        wrapper = cyclone._build_wrapper(types.struct(msg.name), msg)
        if describe(cyclone.wrapper_model(msg), store.message) \
                != cyclonedds_description(wrapper):
            differ.append(msg.name)
    assert len(services) > 50
    assert differ == []


@pytest.mark.parametrize("primitive", [Primitive.LONG_DOUBLE, Primitive.WCHAR])
def test_a_type_cyclone_cannot_carry_is_refused_as_ddstypes_refuses_it(
        primitive: Primitive) -> None:
    msg = MessageType("odd_msgs/msg/Odd", (Field("x", FieldType(primitive)),))
    refused = r"^odd_msgs/msg/Odd\.x: .* is not supported on the wire yet$"
    with pytest.raises(UnsupportedTypeError, match=refused):
        describe(msg, TypeStore().message)


def test_a_sequence_bound_cyclonedds_cannot_declare_is_refused_by_both() -> None:
    # cyclonedds' IDL classes take bounds up to 65535; over it DdsTypes built a class that
    # failed with a TypeError traceback (`topic pub` of such a type), while describe
    # described it: both now refuse it with the field named.
    store = TypeStore()
    over = FieldType(Primitive.INT32, collection=Collection.BOUNDED_SEQUENCE, size=65536)
    msg = MessageType("odd_msgs/msg/Long", (Field("v", over),))
    store.add(msg)
    refused = r"^odd_msgs/msg/Long\.v: a sequence bound of 65536 .* not supported on the wire yet$"
    with pytest.raises(UnsupportedTypeError, match=refused):
        describe(msg, store.message)
    with pytest.raises(UnsupportedTypeError, match=refused):
        DdsTypes(store).struct(msg.name)


def test_the_largest_sequence_bound_is_described_as_cyclonedds_describes_it() -> None:
    store = TypeStore()
    largest = FieldType(Primitive.INT32, collection=Collection.BOUNDED_SEQUENCE, size=65535)
    msg = MessageType("odd_msgs/msg/Longest", (Field("v", largest),))
    store.add(msg)
    assert describe(msg, store.message) \
        == cyclonedds_description(DdsTypes(store).struct(msg.name))
