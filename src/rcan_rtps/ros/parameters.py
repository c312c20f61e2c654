"""A node's parameters, served like rclcpp/rclpy serve them: the six rcl_interfaces services
`<node>/list_parameters`, `get_parameters`, `set_parameters`, `set_parameters_atomically`,
`describe_parameters` and `get_parameter_types`, so `ros2 param` (and `rcan-rtps param`)
lists, reads and sets them. As in rclpy without dynamic typing, a parameter keeps its type;
read-only ones and values a parameter's `check` refuses are refused with a reason.

Served over `ServiceServer`, hence the Cyclone request-reply mapping (see services.py).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from .participant import RosNode
from .service_server import ServiceServer

# rcl_interfaces/msg/ParameterType, and the ParameterValue field of each.
NOT_SET, BOOL, INTEGER, DOUBLE, STRING = 0, 1, 2, 3, 4
BYTE_ARRAY, BOOL_ARRAY, INTEGER_ARRAY, DOUBLE_ARRAY, STRING_ARRAY = 5, 6, 7, 8, 9
VALUE_FIELDS = {
    BOOL: "bool_value", INTEGER: "integer_value", DOUBLE: "double_value",
    STRING: "string_value", BYTE_ARRAY: "byte_array_value", BOOL_ARRAY: "bool_array_value",
    INTEGER_ARRAY: "integer_array_value", DOUBLE_ARRAY: "double_array_value",
    STRING_ARRAY: "string_array_value",
}
TYPE_NAMES = {NOT_SET: "not set", BOOL: "bool", INTEGER: "integer", DOUBLE: "double",
              STRING: "string", BYTE_ARRAY: "byte_array", BOOL_ARRAY: "bool_array",
              INTEGER_ARRAY: "integer_array", DOUBLE_ARRAY: "double_array",
              STRING_ARRAY: "string_array"}
SERVICES = ("list_parameters", "get_parameters", "set_parameters", "set_parameters_atomically",
            "describe_parameters", "get_parameter_types")

Check = Callable[[Any], "str | None"]  # a reason to refuse the value, or None


@dataclass
class Parameter:
    name: str
    value: bool | int | float | str | list[bool] | list[int] | list[float] | list[str]
    description: str = ""
    read_only: bool = False
    check: Check | None = None

    @property
    def type(self) -> int:
        return type_of(self.value)


def type_of(value: Any) -> int:
    if isinstance(value, bool):
        return BOOL
    if isinstance(value, int):
        return INTEGER
    if isinstance(value, float):
        return DOUBLE
    if isinstance(value, str):
        return STRING
    if isinstance(value, (bytes, bytearray)):
        return BYTE_ARRAY
    if isinstance(value, list) and value:
        kinds = {type_of(v) for v in value}
        if len(kinds) == 1:
            return {BOOL: BOOL_ARRAY, INTEGER: INTEGER_ARRAY, DOUBLE: DOUBLE_ARRAY,
                    STRING: STRING_ARRAY}.get(kinds.pop(), NOT_SET)
    return NOT_SET


def to_message(value: Any) -> dict[str, Any]:
    """A plain value as the fields of an rcl_interfaces/msg/ParameterValue."""
    kind = type_of(value)
    field = VALUE_FIELDS.get(kind)
    return {"type": kind, **({field: list(value) if isinstance(value, (list, bytes)) else value}
                             if field else {})}


def from_message(message: Any) -> Any:
    """An rcl_interfaces/msg/ParameterValue (typed) as a plain value (None when not set)."""
    field = VALUE_FIELDS.get(int(message.type))
    if field is None:
        return None
    value = getattr(message, field)
    return list(value) if isinstance(value, (list, tuple, bytes, bytearray)) else value


class ParameterServer:
    """Serves `parameters` on `node`; `on_set(name, value)` runs after each accepted set."""

    def __init__(self, node: RosNode, parameters: list[Parameter],
                 on_set: Callable[[str, Any], None] | None = None) -> None:
        self.node = node
        self.parameters = {p.name: p for p in parameters}
        self._on_set = on_set
        handlers = {
            "list_parameters": self._list, "get_parameters": self._get,
            "set_parameters": self._set, "set_parameters_atomically": self._set_atomically,
            "describe_parameters": self._describe, "get_parameter_types": self._types,
        }
        prefix = node.fqn.rstrip("/")
        self._servers = [
            ServiceServer(node, f"{prefix}/{name}", _service_type(name), handler)
            for name, handler in handlers.items()]

    def value(self, name: str) -> Any:
        return self.parameters[name].value

    # -- the services --------------------------------------------------------------
    async def _list(self, request: Any) -> Mapping[str, Any]:
        prefixes = [p.rstrip(".") for p in request.prefixes]
        depth = int(request.depth)
        names = [n for n in sorted(self.parameters)
                 if (not prefixes or any(n == p or n.startswith(p + ".") for p in prefixes))
                 and (depth == 0 or n.count(".") < depth)]
        groups = sorted({n.rsplit(".", 1)[0] for n in names if "." in n})
        return {"result": {"names": names, "prefixes": groups}}

    async def _get(self, request: Any) -> Mapping[str, Any]:
        return {"values": [to_message(self.parameters[n].value) if n in self.parameters
                           else {"type": NOT_SET} for n in request.names]}

    async def _types(self, request: Any) -> Mapping[str, Any]:
        return {"types": [self.parameters[n].type if n in self.parameters else NOT_SET
                          for n in request.names]}

    async def _describe(self, request: Any) -> Mapping[str, Any]:
        return {"descriptors": [
            {"name": n, "type": p.type, "description": p.description, "read_only": p.read_only}
            if (p := self.parameters.get(n)) is not None else {"name": n, "type": NOT_SET}
            for n in request.names]}

    async def _set(self, request: Any) -> Mapping[str, Any]:
        results = []
        for item in request.parameters:
            reason = self._refusal(item.name, from_message(item.value))
            if reason is None:
                self._assign(item.name, from_message(item.value))
            results.append({"successful": reason is None, "reason": reason or ""})
        return {"results": results}

    async def _set_atomically(self, request: Any) -> Mapping[str, Any]:
        wanted = [(item.name, from_message(item.value)) for item in request.parameters]
        for name, value in wanted:
            reason = self._refusal(name, value)
            if reason is not None:
                return {"result": {"successful": False, "reason": reason}}
        for name, value in wanted:
            self._assign(name, value)
        return {"result": {"successful": True, "reason": ""}}

    def _refusal(self, name: str, value: Any) -> str | None:
        """Why `name` cannot take `value` (rclpy's wording where it has one), or None."""
        parameter = self.parameters.get(name)
        if parameter is None:
            return f"parameter '{name}' is not declared"
        if parameter.read_only:
            return f"parameter '{name}' cannot be set because it is read-only"
        if type_of(value) != parameter.type:
            return (f"Wrong parameter type, parameter {{{name}}} is of type "
                    f"{{{TYPE_NAMES[parameter.type]}}}, setting it to "
                    f"{{{TYPE_NAMES[type_of(value)]}}} is not allowed.")
        return parameter.check(value) if parameter.check is not None else None

    def _assign(self, name: str, value: Any) -> None:
        self.parameters[name].value = value
        if self._on_set is not None:
            self._on_set(name, value)

    async def close(self) -> None:
        await asyncio.gather(*(server.close() for server in self._servers))


def _service_type(name: str) -> str:
    return "rcl_interfaces/srv/" + "".join(part.capitalize() for part in name.split("_"))
