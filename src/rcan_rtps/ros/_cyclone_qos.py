"""Reading a QoS from Cyclone without leaking it: the cyclonedds binding's getters of
USER_DATA, TOPIC_DATA, GROUP_DATA and PARTITION, replaced (`free_what_qos_reads`).

Cyclone's `dds_qget_userdata` (and `topicdata`, `groupdata`) hands back a copy of the bytes,
`dds_qget_partition` a copied array of copied names: the caller owns them and must
`dds_free` them (its own data-representation and property getters do). The binding 11.0.1
never frees these four. It converts a QoS whenever a matched endpoint's data is asked for
(`get_matched_publication_data` and `…_subscription_data`) or a discovery sample is read,
so every endpoint announcing USER_DATA — ours and rmw's all do, `typehash=…;` — leaked its
bytes each time: a service call asks once per matched writer, and a bridge grew by about a
kilobyte per stop for as long as it ran (tests/ros/test_cyclone_qos.py measures it).

The replacements also keep their out-parameters local: the binding's share class-level
holders, which two threads reading QoS at once (the node's reader thread and the loop)
overwrite under each other.
"""

from __future__ import annotations

import ctypes as ct
from collections.abc import Callable
from typing import Any

from cyclonedds.core import Policy
from cyclonedds.qos import _CQos

# (the binding's getter, the C call filling it, the policy its bytes make)
_BYTES_GETTERS: tuple[tuple[str, str, Callable[[bytes], Any]], ...] = (
    ("_get_p_userdata", "_get_userdata", lambda data: Policy.Userdata(data=data)),
    ("_get_p_topicdata", "_get_topicdata", lambda data: Policy.Topicdata(data=data)),
    ("_get_p_groupdata", "_get_groupdata", lambda data: Policy.Groupdata(data=data)),
)


def _bytes_getter(c_call: str, policy: Callable[[bytes], Any]) -> Callable[[Any, Any], Any]:
    def get(cls: Any, qos: Any) -> Any:
        value, size = ct.c_void_p(), ct.c_size_t()
        if not getattr(cls, c_call)(qos, ct.byref(value), ct.byref(size)):
            return None
        if not value:
            return None
        try:
            data = ct.string_at(value, size.value)
        finally:
            cls.free(value)
        return policy(data) if data else None
    return get


def _get_p_partition(cls: Any, qos: Any) -> Any:
    count = ct.c_uint32()
    names = ct.POINTER(ct.c_char_p)()
    if not cls._get_partition(qos, ct.byref(count), ct.byref(names)):
        return None
    if not names:
        return None
    # Each name as the raw pointer it is (a c_char_p element reads as a copy of the bytes).
    pointers = ct.cast(names, ct.POINTER(ct.c_void_p))
    try:
        found = [ct.string_at(pointers[i]).decode() for i in range(count.value)]
    finally:
        for i in range(count.value):
            cls.free(pointers[i])
        cls.free(names)
    return Policy.Partition(partitions=found) if found else None


def free_what_qos_reads() -> None:
    """Puts the non-leaking getters in the binding's place (idempotent)."""
    for name, c_call, policy in _BYTES_GETTERS:
        setattr(_CQos, name, classmethod(_bytes_getter(c_call, policy)))
    setattr(_CQos, "_get_p_partition", classmethod(_get_p_partition))  # noqa: B010


free_what_qos_reads()
