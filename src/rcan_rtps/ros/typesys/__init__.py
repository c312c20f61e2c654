"""ROS interface types: IDL → neutral model → RIHS01 hashes and cyclonedds structs.

Public API::

    parse_idl(text, path) -> ParsedFile       the ROS dialect of OMG IDL
    TypeStore(extra_paths, distro)            one definition per type, loaded lazily
    rihs01(msg, lookup) -> "RIHS01_<hex>"     the type hash rosidl computes
    DdsTypes(store).struct(name)              the cyclonedds `IdlStruct` of a type
    MessageValues(types)                      plain values ⇄ messages, validated with paths
"""

from typing import TYPE_CHECKING, Any

from .ddstypes import DdsTypes
from .hashing import rihs01
from .model import (
    ActionType,
    Collection,
    Constant,
    Field,
    FieldType,
    MessageType,
    ParsedFile,
    Primitive,
    ServiceType,
)
from .store import TypeStore
from .values import MessageValues

if TYPE_CHECKING:
    from .idl_parser import parse_idl

__all__ = [
    "ActionType",
    "Collection",
    "Constant",
    "DdsTypes",
    "Field",
    "FieldType",
    "MessageType",
    "MessageValues",
    "ParsedFile",
    "Primitive",
    "ServiceType",
    "TypeStore",
    "parse_idl",
    "rihs01",
]


def __getattr__(name: str) -> Any:
    """`parse_idl` from its module on first use: a bridge lets the parser go once started
    (`rcan_rtps._modules.START_ONLY`; idle memory, issue 27)."""
    if name == "parse_idl":
        from .idl_parser import parse_idl

        return parse_idl
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
