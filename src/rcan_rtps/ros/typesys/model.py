"""The neutral type model: what a ROS interface *is*, independent of any codec.

The IDL parser produces these objects; the type store derives service, action and
event types from them; the hasher and the cyclonedds type builder consume them.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field


class Primitive(str, enum.Enum):
    """IDL primitive type names as rosidl spells them."""

    BOOLEAN = "boolean"
    OCTET = "octet"
    CHAR = "char"
    WCHAR = "wchar"
    INT8 = "int8"
    UINT8 = "uint8"
    INT16 = "int16"
    UINT16 = "uint16"
    INT32 = "int32"
    UINT32 = "uint32"
    INT64 = "int64"
    UINT64 = "uint64"
    FLOAT = "float"
    DOUBLE = "double"
    LONG_DOUBLE = "long double"
    STRING = "string"
    WSTRING = "wstring"

    @property
    def is_string(self) -> bool:
        return self in (Primitive.STRING, Primitive.WSTRING)

    @property
    def is_integer(self) -> bool:
        return self.value.startswith(("int", "uint")) or self in (Primitive.OCTET, Primitive.CHAR)

    @property
    def is_float(self) -> bool:
        return self in (Primitive.FLOAT, Primitive.DOUBLE, Primitive.LONG_DOUBLE)


INTEGER_RANGES: dict[Primitive, tuple[int, int]] = {
    Primitive.OCTET: (0, 0xFF),
    Primitive.CHAR: (0, 0xFF),
    Primitive.INT8: (-(2**7), 2**7 - 1),
    Primitive.UINT8: (0, 2**8 - 1),
    Primitive.INT16: (-(2**15), 2**15 - 1),
    Primitive.UINT16: (0, 2**16 - 1),
    Primitive.INT32: (-(2**31), 2**31 - 1),
    Primitive.UINT32: (0, 2**32 - 1),
    Primitive.INT64: (-(2**63), 2**63 - 1),
    Primitive.UINT64: (0, 2**64 - 1),
}


class Collection(enum.Enum):
    """How a field repeats its element type."""

    SINGLE = "single"
    ARRAY = "array"  # fixed size, `T name[N]`
    BOUNDED_SEQUENCE = "bounded_sequence"  # `sequence<T, N>`
    SEQUENCE = "sequence"  # `sequence<T>`


@dataclass(frozen=True)
class FieldType:
    """The type of one field: an element (primitive or nested) and how it repeats."""

    primitive: Primitive | None = None
    nested: str | None = None  # full ROS name, e.g. "geometry_msgs/msg/Vector3"
    string_bound: int = 0  # for string<N> / wstring<N>, else 0
    collection: Collection = Collection.SINGLE
    size: int = 0  # array length or sequence bound, else 0

    def __post_init__(self) -> None:
        if (self.primitive is None) == (self.nested is None):
            raise ValueError("a field type is either primitive or nested")

    @property
    def element(self) -> FieldType:
        """The same element type, without repetition."""
        return FieldType(self.primitive, self.nested, self.string_bound)

    @property
    def is_collection(self) -> bool:
        return self.collection is not Collection.SINGLE

    def ros_spelling(self) -> str:
        """A `.msg`-like spelling, used in messages to people."""
        if self.nested is not None:
            base = self.nested
        else:
            assert self.primitive is not None
            base = self.primitive.value
            if self.string_bound:
                base += f"<={self.string_bound}"
        if self.collection is Collection.ARRAY:
            return f"{base}[{self.size}]"
        if self.collection is Collection.BOUNDED_SEQUENCE:
            return f"{base}[<={self.size}]"
        if self.collection is Collection.SEQUENCE:
            return f"{base}[]"
        return base


ConstValue = bool | int | float | str


@dataclass(frozen=True)
class Field:
    name: str
    type: FieldType
    default: object = None  # parsed @default value, or None


@dataclass(frozen=True)
class Constant:
    name: str
    type: FieldType
    value: ConstValue


@dataclass(frozen=True)
class MessageType:
    """One struct, named the ROS way: `pkg/msg/Name`, `pkg/srv/Name_Request`, …"""

    name: str
    fields: tuple[Field, ...]
    constants: tuple[Constant, ...] = ()
    source: str = ""  # where it was defined, for error messages

    @property
    def package(self) -> str:
        return self.name.split("/", 1)[0]

    @property
    def dds_name(self) -> str:
        """`pkg/msg/T` → `pkg::msg::dds_::T_`, the DDS type name every RMW uses."""
        pkg, kind, short = self.name.split("/")
        return f"{pkg}::{kind}::dds_::{short}_"

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(name)

    def nested_names(self) -> list[str]:
        return [f.type.nested for f in self.fields if f.type.nested is not None]


@dataclass(frozen=True)
class ServiceType:
    name: str  # pkg/srv/Name (or pkg/action/Name_SendGoal …)
    request: MessageType
    response: MessageType
    event: MessageType


@dataclass(frozen=True)
class ActionType:
    name: str  # pkg/action/Name
    goal: MessageType
    result: MessageType
    feedback: MessageType
    send_goal: ServiceType
    get_result: ServiceType
    feedback_message: MessageType


@dataclass
class ParsedFile:
    """Everything one `.idl` file defines, before service/action types are derived."""

    path: str
    structs: dict[str, MessageType] = field(default_factory=dict)
    includes: list[str] = field(default_factory=list)
