"""RIHS01 type hashes, as rosidl computes them from the IDL form of a type (REP-2011)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable

from .model import Collection, FieldType, MessageType, Primitive

_BASE_IDS: dict[Primitive, int] = {
    Primitive.INT8: 2,
    Primitive.UINT8: 3,
    Primitive.INT16: 4,
    Primitive.UINT16: 5,
    Primitive.INT32: 6,
    Primitive.UINT32: 7,
    Primitive.INT64: 8,
    Primitive.UINT64: 9,
    Primitive.FLOAT: 10,
    Primitive.DOUBLE: 11,
    Primitive.LONG_DOUBLE: 12,
    Primitive.CHAR: 13,
    Primitive.WCHAR: 14,
    Primitive.BOOLEAN: 15,
    Primitive.OCTET: 16,
    Primitive.STRING: 17,
    Primitive.WSTRING: 18,
}
_NESTED_ID = 1
_BOUNDED_STRING_ID = {Primitive.STRING: 21, Primitive.WSTRING: 22}
_COLLECTION_OFFSET = {
    Collection.SINGLE: 0,
    Collection.ARRAY: 48,
    Collection.BOUNDED_SEQUENCE: 96,
    Collection.SEQUENCE: 144,
}


def type_id(ftype: FieldType) -> int:
    if ftype.nested is not None:
        base = _NESTED_ID
    else:
        assert ftype.primitive is not None
        if ftype.string_bound:
            base = _BOUNDED_STRING_ID[ftype.primitive]
        else:
            base = _BASE_IDS[ftype.primitive]
    return base + _COLLECTION_OFFSET[ftype.collection]


def type_description(msg: MessageType) -> dict[str, object]:
    """The hashed part of a type description: names and field types, no defaults."""
    return {
        "type_name": msg.name,
        "fields": [
            {
                "name": f.name,
                "type": {
                    "type_id": type_id(f.type),
                    "capacity": f.type.size,
                    "string_capacity": f.type.string_bound,
                    "nested_type_name": f.type.nested or "",
                },
            }
            for f in msg.fields
        ],
    }


def referenced_types(msg: MessageType, lookup: Callable[[str], MessageType]) -> list[MessageType]:
    """Every type `msg` depends on, transitively, sorted by name, itself excluded."""
    seen: dict[str, MessageType] = {}
    stack = list(msg.nested_names())
    while stack:
        name = stack.pop()
        if name in seen or name == msg.name:
            continue
        nested = lookup(name)
        seen[name] = nested
        stack.extend(nested.nested_names())
    return [seen[n] for n in sorted(seen)]


def rihs01(msg: MessageType, lookup: Callable[[str], MessageType]) -> str:
    """`RIHS01_<sha256 hex>` of `msg`; `lookup` resolves nested type names."""
    document = {
        "type_description": type_description(msg),
        "referenced_type_descriptions": [
            type_description(t) for t in referenced_types(msg, lookup)
        ],
    }
    text = json.dumps(document, separators=(", ", ": "))
    return "RIHS01_" + hashlib.sha256(text.encode("utf-8")).hexdigest()
