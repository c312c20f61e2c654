"""What the generated encoders and decoders share: the module text being written, and the
queue that writes one function per struct type, each whole before the next begins."""

from __future__ import annotations

from typing import Any

from .model import MessageType
from .store import TypeStore


class Source:
    """Lines of one generated module and the constants its code refers to."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.namespace: dict[str, Any] = {}
        self._count = 0

    def name(self, prefix: str) -> str:
        self._count += 1
        return f"{prefix}{self._count}"

    def const(self, value: Any, prefix: str = "K") -> str:
        name = self.name(prefix)
        self.namespace[name] = value
        return name

    def emit(self, indent: int, line: str) -> None:
        self.lines.append("    " * indent + line)

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


class FunctionWriter:
    """Names a function per (type, top level) on first request and writes its body once the
    body being written is done: a body that needs a nested type's function asks for it and
    goes on. A `top` function starts at body offset 0 (its first run needs no lookup)."""

    prefix = "fn_"

    def __init__(self, store: TypeStore, source: Source) -> None:
        self.store = store
        self.src = source
        self.functions: dict[tuple[str, bool], str] = {}
        self._pending: list[tuple[str, str, bool]] = []  # function name, type, top level

    def function(self, type_name: str, *, top: bool = False) -> str:
        found = self.functions.get((type_name, top))
        if found is None:
            found = self.src.name(self.prefix)
            self.functions[(type_name, top)] = found
            self._pending.append((found, type_name, top))
            if len(self._pending) == 1:  # not inside another body: write them all now
                while self._pending:
                    name, pending_type, pending_top = self._pending[0]
                    self.body(name, self.store.message(pending_type), pending_top)
                    self._pending.pop(0)
        return found

    def body(self, name: str, msg: MessageType, top: bool) -> None:
        raise NotImplementedError
