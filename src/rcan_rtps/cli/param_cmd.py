"""`rcan-rtps param list|get|set|dump`, shaped like `ros2 param`, over the rcl_interfaces
services every ROS 2 node serves (`<node>/list_parameters`, `get_parameters`, …).

Any participant may serve those services under any node's name and answer what it likes:
names and values are printed as `_printable.shown` makes them (never an escape sequence
obeyed); a type rcl_interfaces does not define, or a `get_parameters` reply with another
count of values than names asked for, is an error naming the node, not a traceback or a
value shown as another; `dump` writes a name that nests below another parameter's value
(`a` and `a.b`) dotted, as a params file may (rcl joins nested keys with dots)."""

from __future__ import annotations

import argparse
import asyncio
import re
import time
from typing import Any

import yaml

from .. import _stop_signals as stop_signals
from .._printable import shown
from ..ros.errors import GraphTimeout, WireError, seconds
from ..ros.graph import RosGraph
from ..ros.parameters import (
    BOOL,
    BOOL_ARRAY,
    BYTE_ARRAY,
    DOUBLE,
    DOUBLE_ARRAY,
    INTEGER,
    INTEGER_ARRAY,
    NOT_SET,
    STRING,
    STRING_ARRAY,
    VALUE_FIELDS,
)
from ..ros.participant import RosNode
from ..ros.services import ServiceClient
from ._common import make_node

# How long a parameter command looks for its node's services on the graph before saying the
# node is not there (as `service call` looks for a server; --timeout, when shorter, wins).
NODE_PATIENCE = 3.0

# ros2 param get's wording, by type.
GET_LABELS = {
    BOOL: "Boolean value is:", INTEGER: "Integer value is:", DOUBLE: "Double value is:",
    STRING: "String value is:", BYTE_ARRAY: "Byte values are:",
    BOOL_ARRAY: "Boolean values are:", INTEGER_ARRAY: "Integer values are:",
    DOUBLE_ARRAY: "Double values are:", STRING_ARRAY: "String values are:",
}


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("param", help="read and change a node's parameters")
    actions = parser.add_subparsers(dest="param_command", required=True)

    listing = actions.add_parser("list", help="parameter names of a node")
    listing.add_argument("node", metavar="NODE_NAME", help="the node, e.g. /robot1/controller")
    listing.add_argument("--filter", default="", help="only names matching this regex")
    _common_options(listing)
    listing.set_defaults(func=lambda a: stop_signals.run(_list(a)))

    get = actions.add_parser("get", help="value of a parameter")
    get.add_argument("node", metavar="NODE_NAME", help="the node, e.g. /robot1/controller")
    get.add_argument("name", metavar="PARAMETER_NAME", help="the parameter (dotted for nested)")
    get.add_argument("--hide-type", action="store_true", help="print the value only")
    _common_options(get)
    get.set_defaults(func=lambda a: stop_signals.run(_get(a)))

    set_ = actions.add_parser("set", help="set a parameter (VALUE is YAML)")
    set_.add_argument("node", metavar="NODE_NAME", help="the node, e.g. /robot1/controller")
    set_.add_argument("name", metavar="PARAMETER_NAME", help="the parameter (dotted for nested)")
    set_.add_argument("value", metavar="VALUE", help="a YAML value: 0.5, true, hello, [1, 2]")
    _common_options(set_)
    set_.set_defaults(func=lambda a: stop_signals.run(_set(a)))

    dump = actions.add_parser("dump", help="every parameter of a node, as a params file")
    dump.add_argument("node", metavar="NODE_NAME", help="the node, e.g. /robot1/controller")
    _common_options(dump)
    dump.set_defaults(func=lambda a: stop_signals.run(_dump(a)))


def _common_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--timeout", type=float, default=10.0,
                        help="seconds to wait for the node's services (default 10)")


async def _await_parameter_server(node: RosNode, target: str, patience: float) -> None:
    """Waits (up to `patience` s) for `target`'s parameter services on the graph: a node not
    there is named as one (the user named a node, not a service), as `service call` does."""
    graph = RosGraph(node)
    service = f"{target}/get_parameters"
    deadline = time.monotonic() + patience
    while True:
        graph.refresh()
        if service in graph.services(include_hidden=True):
            return
        if time.monotonic() >= deadline:
            raise GraphTimeout(f"no node {target} serves parameters within {seconds(patience)}; "
                               "`rcan-rtps node list` shows the nodes there are")
        await asyncio.sleep(0.1)


def _node_fqn(name: str) -> str:
    return name if name.startswith("/") else "/" + name


async def _call(node: RosNode, target: str, service: str, values: dict[str, Any],
                timeout: float) -> dict[str, Any]:
    await _await_parameter_server(node, _node_fqn(target), min(timeout, NODE_PATIENCE))
    kind = "".join(part.capitalize() for part in service.split("_"))
    client = ServiceClient(node, f"{_node_fqn(target)}/{service}", f"rcl_interfaces/srv/{kind}")
    try:
        response = await client.call(values, timeout)
        return node.values.to_plain(client.response_type, response)
    finally:
        client.close()


async def parameter_names(node: RosNode, target: str, timeout: float) -> list[str]:
    reply = await _call(node, target, "list_parameters", {"prefixes": [], "depth": 0}, timeout)
    return sorted(reply["result"]["names"])


def to_python(value: dict[str, Any]) -> Any:
    """A ParameterValue as a plain value (None when not set)."""
    field = VALUE_FIELDS.get(value["type"])
    return None if field is None else value[field]


def known_type(target: str, name: str, value: dict[str, Any]) -> int:
    """The type of a ParameterValue `target` answered for `name`: one rcl_interfaces defines,
    else a WireError (a node answering another number answers nothing we can show)."""
    kind = int(value["type"])
    if kind != NOT_SET and kind not in VALUE_FIELDS:
        raise WireError(f"{shown(_node_fqn(target))} answered parameter {shown(name)} with "
                        f"type {kind}, which rcl_interfaces/msg/ParameterType does not define")
    return kind


def answered_values(target: str, names: list[str], reply: dict[str, Any]
                    ) -> list[dict[str, Any]]:
    """A get_parameters reply's values, one per name asked for; a WireError when the node
    answered another count (pairing them up would show values under the wrong names, or
    leave parameters out unsaid)."""
    values: list[dict[str, Any]] = reply["values"]
    if len(values) != len(names):
        raise WireError(f"{shown(_node_fqn(target))} answered {len(values)} value(s) for "
                        f"the {len(names)} parameter(s) asked for")
    for name, value in zip(names, values, strict=True):
        known_type(target, name, value)
    return values


def to_parameter_value(value: Any) -> dict[str, Any]:
    """A YAML value as a ParameterValue, typed like ros2 param set types it."""
    if isinstance(value, bool):
        return {"type": BOOL, "bool_value": value}
    if isinstance(value, int):
        return {"type": INTEGER, "integer_value": value}
    if isinstance(value, float):
        return {"type": DOUBLE, "double_value": value}
    if isinstance(value, list) and value:
        kind = _array_kind(value)
        items = [float(v) for v in value] if kind == DOUBLE_ARRAY else value
        return {"type": kind, VALUE_FIELDS[kind]: items}
    return {"type": STRING, "string_value": "" if value is None else str(value)}


def _array_kind(values: list[Any]) -> int:
    if all(isinstance(v, bool) for v in values):
        return BOOL_ARRAY
    numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if len(numbers) == len(values):
        return INTEGER_ARRAY if all(isinstance(v, int) for v in numbers) else DOUBLE_ARRAY
    if all(isinstance(v, str) for v in values):
        return STRING_ARRAY
    raise ValueError("array parameters must hold values of one type")


def _format_value(kind: int, value: Any) -> str:
    if kind == BOOL:
        return str(bool(value))
    if kind == BYTE_ARRAY:
        return str([bytes([b]) for b in value])
    return str(value)


async def _list(args: argparse.Namespace) -> int:
    pattern = re.compile(args.filter) if args.filter else None
    with make_node(args) as node:
        for name in await parameter_names(node, args.node, args.timeout):
            if pattern is None or pattern.search(name):
                print(f"  {shown(name)}")
    return 0


async def _get(args: argparse.Namespace) -> int:
    with make_node(args) as node:
        reply = await _call(node, args.node, "get_parameters", {"names": [args.name]},
                            args.timeout)
    [value] = answered_values(args.node, [args.name], reply)
    kind = value["type"]
    if kind == NOT_SET:
        print("Parameter not set.")
        return 1
    text = shown(_format_value(kind, to_python(value)))
    print(text if args.hide_type else f"{GET_LABELS[kind]} {text}")
    return 0


async def _set(args: argparse.Namespace) -> int:
    value = to_parameter_value(yaml.safe_load(args.value) if args.value.strip() else "")
    with make_node(args) as node:
        reply = await _call(node, args.node, "set_parameters",
                            {"parameters": [{"name": args.name, "value": value}]}, args.timeout)
    result = reply["results"][0] if reply["results"] else {"successful": False, "reason": ""}
    if result["successful"]:
        print("Set parameter successful")
        return 0
    reason = f": {result['reason']}" if result["reason"] else ""
    print(f"Setting parameter failed{reason}")
    return 1


def _nest(flat: dict[str, Any]) -> dict[str, Any]:
    """`a.b.c: v` → {a: {b: {c: v}}}, as ros2 param dump writes dotted names. A name below
    another parameter's value (`a.b` beside `a`: a node may declare both) stays dotted at
    the deepest level that is not a value (`a: 1`, `a.b: 2`), which rcl reads back as `a.b`."""
    tree: dict[str, Any] = {}
    for name, value in sorted(flat.items()):
        parts = name.split(".")
        level = tree
        while len(parts) > 1 and isinstance(level.setdefault(parts[0], {}), dict):
            level = level[parts.pop(0)]
        level[".".join(parts)] = value
    return tree


async def _dump(args: argparse.Namespace) -> int:
    with make_node(args) as node:
        names = await parameter_names(node, args.node, args.timeout)
        reply = await _call(node, args.node, "get_parameters", {"names": names}, args.timeout)
    values = {n: to_python(v) for n, v in zip(names, answered_values(args.node, names, reply),
                                              strict=True) if v["type"] != NOT_SET}
    document = {_node_fqn(args.node): {"ros__parameters": _nest(values)}}
    print(yaml.safe_dump(document, sort_keys=False, default_flow_style=False).rstrip())
    return 0
