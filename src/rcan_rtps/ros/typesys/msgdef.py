"""`.msg` text from the type model: the `ros2msg` schema of MCAP's ROS 2 profile.

A bag stores, per type, the type's `.msg` definition followed by every type it depends
on, each after a line of 80 `=` and a `MSG: pkg/Type` line (the format of ROS 1's
`gendeps --cat`, which rosbag2 keeps). rosbag2 copies the installed `.msg` files; we have
only IDL, so the text is generated: same fields, types, defaults and constants, no
comments. Dependencies come depth first, siblings in name order, each once, as rosbag2
orders them. IDL cannot tell a `.msg` `char` from `uint8` (rosidl maps both to `uint8`);
both are one unsigned byte on the wire, so readers decode them alike.
"""

from __future__ import annotations

from collections.abc import Callable

from .model import Collection, FieldType, MessageType, Primitive

DELIMITER = "=" * 80
PLACEHOLDER = "structure_needs_at_least_one_member"
_MSG_PRIMITIVES = {
    Primitive.BOOLEAN: "bool",
    Primitive.OCTET: "byte",
    Primitive.FLOAT: "float32",
    Primitive.DOUBLE: "float64",
}

Lookup = Callable[[str], MessageType]


def resource_name(full: str) -> str:
    """`pkg/msg/T` → `pkg/T`, how `.msg` files name other messages."""
    pkg, _, short = full.split("/")
    return f"{pkg}/{short}"


def _element_spelling(ftype: FieldType, package: str) -> str:
    if ftype.nested is not None:
        pkg, _, short = ftype.nested.split("/")
        return short if pkg == package else f"{pkg}/{short}"
    assert ftype.primitive is not None
    base = _MSG_PRIMITIVES.get(ftype.primitive, ftype.primitive.value)
    return f"{base}<={ftype.string_bound}" if ftype.string_bound else base


def type_spelling(ftype: FieldType, package: str) -> str:
    base = _element_spelling(ftype, package)
    suffix = {
        Collection.SINGLE: "",
        Collection.ARRAY: f"[{ftype.size}]",
        Collection.BOUNDED_SEQUENCE: f"[<={ftype.size}]",
        Collection.SEQUENCE: "[]",
    }[ftype.collection]
    return base + suffix


def _literal(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_literal(v) for v in value) + "]"
    return repr(value)


def msg_text(msg: MessageType) -> str:
    """One type's `.msg` body (fields after constants), newline-terminated."""
    lines = [f"{type_spelling(c.type, msg.package)} {c.name}={_literal(c.value)}"
             for c in msg.constants]
    for f in msg.fields:
        if f.name == PLACEHOLDER and len(msg.fields) == 1:
            continue  # rosidl's member of an empty struct: not in the .msg
        line = f"{type_spelling(f.type, msg.package)} {f.name}"
        if f.default is not None:
            line += f" {_literal(f.default)}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def full_definition(name: str, lookup: Lookup) -> str:
    """The concatenated definition of `name` and everything it depends on."""
    root = lookup(name)
    parts = [msg_text(root)]
    seen: set[str] = set()

    def append_dependencies(msg: MessageType) -> None:
        for dep in sorted(set(msg.nested_names()), key=resource_name):
            if dep in seen:
                continue
            seen.add(dep)
            nested = lookup(dep)
            parts.append(f"\n{DELIMITER}\nMSG: {resource_name(dep)}\n{msg_text(nested)}")
            append_dependencies(nested)

    append_dependencies(root)
    return "".join(parts)
