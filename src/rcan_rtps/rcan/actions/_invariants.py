"""The §8 checks an action may declare, and the parameters each one reads.

A check is only as good as what it can see. Each invariant declares the fields it reads and the
kind of value it understands in each (`READS`); the check itself lives in
`governance.invariants`. Two gates keep a check from passing what it does not understand:

- at declaration: an `ActionSpec` whose parameter type lacks a field a declared check reads, or
  types it as something the check does not understand, is refused (`unreadable`) — the action's
  module does not import, so the registry never holds it;
- at run time: the check refuses parameters that do not hold what it reads (`not_understood`),
  whatever their type, rather than passing them as "not mine".
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import msgspec
import msgspec.inspect as mi


class Invariant(enum.Enum):
    """The §8 checks an action's parameters go through (see governance.invariants)."""

    ESTOP_GUARD = "estop_guard"  # refused while the e-stop is latched
    FINITE = "finite"  # every number finite (behind the schema's bounds)
    VELOCITY = "velocity"  # linear/angular limits: clamp, or deny >10 % over
    WORKSPACE = "workspace"  # goal strictly inside the workspace polygon
    JOINT_GROUP = "joint_group"  # the arm exists and owns every joint named
    DURATION = "duration"  # a timed move lasts at most safety.max_move_duration_s
    ACCELERATION = "acceleration"  # a velocity stream ramps within safety.max_*_accel


class Kind(enum.Enum):
    """A kind of value a check understands."""

    NUMBER = "a number"  # int or float; never a bool
    TEXT = "text"
    TEXT_LIST = "a list of text"


@dataclass(frozen=True)
class Field:
    """One field a check reads; `nullable`: None is a value it understands (e.g. no group)."""

    name: str
    kind: Kind
    nullable: bool = False

    def describe(self) -> str:
        return f"`{self.name}` ({self.kind.value}{' or null' if self.nullable else ''})"


@dataclass(frozen=True)
class Reads:
    """What a check reads: named fields, and/or every number at any depth (`every_number`)."""

    fields: tuple[Field, ...] = ()
    every_number: bool = False

    def describe(self) -> str:
        parts = [f.describe() for f in self.fields]
        if self.every_number:
            parts.append("every number")
        return ", ".join(parts) or "no parameters"


_VELOCITY = (Field("linear_x", Kind.NUMBER), Field("linear_y", Kind.NUMBER),
             Field("angular_z", Kind.NUMBER))
_DURATION = Field("duration_s", Kind.NUMBER, nullable=True)  # None: held until stopped

READS: Mapping[Invariant, Reads] = MappingProxyType({
    Invariant.ESTOP_GUARD: Reads(),  # the latch, not the parameters
    Invariant.FINITE: Reads(every_number=True),
    Invariant.VELOCITY: Reads(_VELOCITY),
    # A goal without a frame cannot be placed in the workspace's: frame_id is read too.
    Invariant.WORKSPACE: Reads((Field("x", Kind.NUMBER), Field("y", Kind.NUMBER),
                                Field("frame_id", Kind.TEXT, nullable=True))),
    Invariant.JOINT_GROUP: Reads((Field("joints", Kind.TEXT_LIST),
                                  Field("group", Kind.TEXT, nullable=True))),
    Invariant.DURATION: Reads((_DURATION,)),
    Invariant.ACCELERATION: Reads((*_VELOCITY, _DURATION)),
})
if set(READS) != set(Invariant):
    raise ValueError("every invariant must declare what it reads")


# -- at declaration: the parameter type -------------------------------------------------------


def unreadable(params: type[Any], invariant: Invariant) -> str | None:
    """Why `invariant`'s check could not read every value of type `params`; None if it can."""
    reads = READS[invariant]
    info = mi.type_info(params)
    if not isinstance(info, mi.StructType):
        return f"{params.__name__} is not a msgspec struct"
    declared = {f.name: f.type for f in info.fields}
    for want in reads.fields:
        if want.name not in declared:
            return f"{params.__name__} has no field {want.describe()}"
        problem = _type_problem(declared[want.name], want)
        if problem:
            return f"{params.__name__}.{want.name} {problem}, not {want.kind.value}"
    if reads.every_number:
        where = _unwalkable(info, params.__name__, set())
        if where:
            return f"{where} holds values it cannot walk for numbers"
    return None


_KIND_TYPES: Mapping[Kind, tuple[type[mi.Type], ...]] = {
    Kind.NUMBER: (mi.FloatType, mi.IntType),
    Kind.TEXT: (mi.StrType,),
}


def _type_problem(declared: mi.Type, want: Field) -> str | None:
    options = declared.types if isinstance(declared, mi.UnionType) else (declared,)
    for option in options:
        if isinstance(option, mi.NoneType):
            if not want.nullable:
                return "may be null"
        elif not _kind_matches(option, want.kind):
            return f"is typed {type(option).__name__}"
    return None


def _kind_matches(option: mi.Type, kind: Kind) -> bool:
    if kind is Kind.TEXT_LIST:
        return isinstance(option, mi.ListType) and isinstance(option.item_type, mi.StrType)
    if isinstance(option, mi.LiteralType):  # e.g. Literal["map", "odom"]: text, or numbers
        wanted = str if kind is Kind.TEXT else (int, float)
        return all(isinstance(v, wanted) and not isinstance(v, bool) for v in option.values)
    return isinstance(option, _KIND_TYPES[kind])


_LEAVES = (mi.FloatType, mi.IntType, mi.BoolType, mi.StrType, mi.NoneType, mi.LiteralType)


def _unwalkable(info: mi.Type, where: str, seen: set[type[Any]]) -> str | None:
    """The first place the finite check's walk (`numbers`) would not understand."""
    if isinstance(info, _LEAVES):
        return None
    if isinstance(info, mi.StructType):
        if info.cls in seen:
            return None
        seen.add(info.cls)
        return next((w for f in info.fields
                     if (w := _unwalkable(f.type, f"{where}.{f.name}", seen))), None)
    if isinstance(info, mi.UnionType):
        return next((w for t in info.types if (w := _unwalkable(t, where, seen))), None)
    if isinstance(info, mi.ListType | mi.VarTupleType):
        return _unwalkable(info.item_type, f"{where}[]", seen)
    if isinstance(info, mi.TupleType):
        return next((w for t in info.item_types if (w := _unwalkable(t, f"{where}[]", seen))),
                    None)
    if isinstance(info, mi.DictType):
        return _unwalkable(info.value_type, f"{where}{{}}", seen)
    return where


# -- at run time: the value -------------------------------------------------------------------


def not_understood(params: Any, invariant: Invariant) -> str | None:
    """Why `invariant`'s check cannot read `params` as they are; None if it can."""
    reads = READS[invariant]
    if not isinstance(params, msgspec.Struct):
        return f"parameters of type {type(params).__name__} are not an action's"
    for want in reads.fields:
        if not hasattr(params, want.name):
            return f"{type(params).__name__} has no field {want.describe()}"
        value = getattr(params, want.name)
        if not (value is None and want.nullable) and not _value_matches(value, want.kind):
            return f"{type(params).__name__}.{want.name} is {value!r}, not {want.kind.value}"
    if reads.every_number:
        try:
            for _ in numbers(params):
                pass
        except TypeError as exc:
            return str(exc)
    return None


def _value_matches(value: Any, kind: Kind) -> bool:
    if kind is Kind.NUMBER:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if kind is Kind.TEXT:
        return isinstance(value, str)
    return isinstance(value, list | tuple) and all(isinstance(v, str) for v in value)


@functools.cache
def _flags(kind: type[msgspec.Struct]) -> frozenset[str]:
    """The fields of a params struct declared `bool`: a flag there is no number."""
    info = mi.type_info(kind)
    assert isinstance(info, mi.StructType)
    return frozenset(f.name for f in info.fields if isinstance(f.type, mi.BoolType))


def numbers(value: Any) -> Iterator[Any]:
    """Every int or float inside a params struct, at any depth — a bool too, unless its field
    is declared `bool` (then it is a flag, not a number posing as one); TypeError at a value
    it does not know how to walk (it would otherwise go unchecked)."""
    if isinstance(value, msgspec.Struct):
        flags = _flags(type(value))
        items: Any = [getattr(value, name) for name in value.__struct_fields__
                      if not (name in flags and isinstance(getattr(value, name), bool))]
    elif isinstance(value, dict):
        items = value.values()
    elif isinstance(value, list | tuple):
        items = value
    elif isinstance(value, int | float):
        yield value
        return
    elif value is None or isinstance(value, str):
        return
    else:
        raise TypeError(f"a value of type {type(value).__name__} cannot be checked for numbers")
    for item in items:
        if isinstance(item, int | float):  # the usual case: a flat struct of numbers
            yield item
        elif item is not None and not isinstance(item, str):
            yield from numbers(item)
