"""The type store: one definition per ROS type, loaded lazily from IDL search paths.

Search order (first hit wins): extra directories (`--idl-path`, `RCAN_RTPS_IDL_PATH`),
then the bundle's overrides for the configured distro, then the bundle itself. A
directory may be laid out like the bundle (`<dir>/<pkg>/<kind>/<Name>.idl`, which is
also the layout of a ROS install's `share/`) or be one package (`<dir>/<kind>/…`).
Service, action and event types are derived from their `.idl` like rosidl does.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

from ..errors import UnknownTypeError, UnsupportedDistroError
from .hashing import rihs01
from .model import (
    ActionType,
    Collection,
    Field,
    FieldType,
    MessageType,
    Primitive,
    ServiceType,
)

KINDS = ("msg", "srv", "action")
DISTROS = ("humble", "jazzy", "kilted")
DEFAULT_DISTRO = "jazzy"
_UUID = "unique_identifier_msgs/msg/UUID"
_TIME = "builtin_interfaces/msg/Time"
_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"

_SERVICE_SUFFIXES = ("_Request", "_Response", "_Event")
_ACTION_SUFFIXES = (
    "_Goal", "_Result", "_Feedback", "_FeedbackMessage",
    "_SendGoal_Request", "_SendGoal_Response", "_SendGoal_Event", "_SendGoal",
    "_GetResult_Request", "_GetResult_Response", "_GetResult_Event", "_GetResult",
)


def bundle_dir() -> Path:
    """The shipped IDL bundle: inside the wheel, or at the top of a source checkout."""
    here = Path(__file__).resolve()
    wheel = here.parents[2] / "_idl"
    if wheel.is_dir():
        return wheel
    return here.parents[4] / "idl"


def resolve_distro(explicit: str | None = None) -> str:
    distro = (explicit or os.environ.get("ROS_DISTRO") or DEFAULT_DISTRO).lower()
    if distro not in DISTROS:
        choices = ", ".join(DISTROS)
        raise UnsupportedDistroError(f"unsupported ROS distro {distro!r}; choose one of {choices}")
    return distro


def env_idl_paths() -> list[Path]:
    raw = os.environ.get("RCAN_RTPS_IDL_PATH", "")
    return [Path(p) for p in raw.split(os.pathsep) if p]


def normalize_name(name: str) -> str:
    """Accepts `pkg/msg/T`, `pkg/T` (a message) and `pkg::msg::dds_::T_`."""
    if "::" in name:
        parts = [p for p in name.split("::") if p != "dds_"]
        if len(parts) == 3:
            short = parts[2][:-1] if parts[2].endswith("_") else parts[2]
            return f"{parts[0]}/{parts[1]}/{short}"
    parts = name.strip("/").split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return "/".join(parts)


def _single(nested: str) -> FieldType:
    return FieldType(nested=nested)


def _struct(name: str, *fields: tuple[str, FieldType]) -> MessageType:
    return MessageType(name, tuple(Field(n, t) for n, t in fields), (), "<derived>")


class TypeStore:
    """Thread-safe, lazily filled map from ROS type names to their definitions."""

    def __init__(self, extra_paths: Iterable[str | Path] = (), distro: str | None = None,
                 *, include_bundle: bool = True) -> None:
        self.distro = resolve_distro(distro)
        roots = [Path(p) for p in extra_paths]
        if include_bundle:
            bundle = bundle_dir()
            roots += [bundle / "_distro" / self.distro, bundle]
        self.roots = roots
        self._types: dict[str, MessageType] = {}
        self._lock = threading.RLock()

    # -- files ------------------------------------------------------------------
    def _path_of(self, interface: str) -> Path | None:
        """The file of `interface` (`pkg/kind/T`): the first root that holds it, as the full
        scan (`interface_names`) would find it. Looked up, not indexed: a run needs a dozen of
        the ~360 bundled files, and an index of them all held ~85 kB at idle."""
        parts = interface.split("/")
        if len(parts) != 3 or parts[1] not in KINDS:
            return None
        pkg, kind, name = parts
        if not pkg or pkg.startswith(("_", ".")) or not name or name.startswith("."):
            return None
        for root in self.roots:
            package = _package_dir(root, pkg)
            if package is not None and (package / kind / f"{name}.idl").is_file():
                return package / kind / f"{name}.idl"
        return None

    def interface_names(self) -> list[str]:
        """Every interface (`pkg/msg/T`, `pkg/srv/S`, `pkg/action/A`) found on the paths."""
        return sorted({name for root in self.roots for name, _ in _scan(root)})

    def source_of(self, interface: str) -> Path:
        path = self._path_of(normalize_name(interface))
        if path is None:
            raise UnknownTypeError(interface, self.interface_names())
        return path

    # -- lookups --------------------------------------------------------------
    def message(self, name: str) -> MessageType:
        """Any struct type, including derived ones (`pkg/srv/S_Request`, `pkg/action/A_Goal`)."""
        name = normalize_name(name)
        with self._lock:
            found = self._types.get(name)
            if found is None:
                self._load_for(name)
                found = self._types.get(name)
            if found is None:
                raise UnknownTypeError(name, self._known_names())
            return found

    def service(self, name: str) -> ServiceType:
        name = normalize_name(name)
        base = self.message(name)  # the derived `pkg/srv/S` struct
        return ServiceType(base.name, self.message(name + "_Request"),
                           self.message(name + "_Response"), self.message(name + "_Event"))

    def action(self, name: str) -> ActionType:
        name = normalize_name(name)
        self.message(name)
        return ActionType(
            name,
            self.message(name + "_Goal"),
            self.message(name + "_Result"),
            self.message(name + "_Feedback"),
            self.service(name + "_SendGoal"),
            self.service(name + "_GetResult"),
            self.message(name + "_FeedbackMessage"),
        )

    def load_nested(self, name: str) -> None:
        """Loads `name` and every type it nests, now: the types of endpoints made later (a
        service's, by its first call) are then built without parsing anything."""
        todo, seen = [normalize_name(name)], set()
        while todo:
            current = todo.pop()
            if current in seen:
                continue
            seen.add(current)
            todo += [f.type.nested for f in self.message(current).fields
                     if f.type.nested is not None]

    def require(self, name: str) -> str:
        """`name` normalized, once it is known or its file is found; raises UnknownTypeError.
        Parses nothing: for a type whose definition is wanted only later (an action client's
        own action, parsed by its first goal)."""
        name = normalize_name(name)
        with self._lock:
            if name in self._types or self._path_of(_interface_of(name)) is not None:
                return name
            raise UnknownTypeError(name, self._known_names())

    def hash_of(self, name: str) -> str:
        return rihs01(self.message(name), self.message)

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        try:
            self.message(name)
        except UnknownTypeError:
            return False
        return True

    def add(self, msg: MessageType) -> None:
        with self._lock:
            self._types[msg.name] = msg

    def _known_names(self) -> list[str]:
        return sorted(set(self.interface_names()) | set(self._types))

    # -- loading ----------------------------------------------------------------
    def _load_for(self, name: str) -> None:
        interface = _interface_of(name)
        path = self._path_of(interface)
        if path is None:
            return
        # Imported by the first type a process loads: a bridge's start loads every type its
        # stops use, then lets the parser go (`rcan_rtps._modules.START_ONLY`; idle memory,
        # issue 27); a later first use (a goal, an arm command) imports it again.
        from .idl_parser import parse_idl

        parsed = parse_idl(path.read_text(encoding="utf-8"), str(path))
        for struct in parsed.structs.values():
            self._types.setdefault(struct.name, struct)
        kind = interface.split("/")[1]
        if kind == "srv":
            self._derive_service(interface)
        elif kind == "action":
            self._derive_action(interface)

    def _derive_service(self, name: str) -> None:
        req, resp = name + "_Request", name + "_Response"
        for part in (req, resp):
            if part not in self._types:
                raise UnknownTypeError(part, self._known_names())
        self._types[name + "_Event"] = _struct(
            name + "_Event",
            ("info", _single(_EVENT_INFO)),
            ("request", FieldType(nested=req, collection=Collection.BOUNDED_SEQUENCE, size=1)),
            ("response", FieldType(nested=resp, collection=Collection.BOUNDED_SEQUENCE, size=1)),
        )
        self._types[name] = _struct(
            name,
            ("request_message", _single(req)),
            ("response_message", _single(resp)),
            ("event_message", _single(name + "_Event")),
        )

    def _derive_action(self, name: str) -> None:
        for part in ("_Goal", "_Result", "_Feedback"):
            if name + part not in self._types:
                raise UnknownTypeError(name + part, self._known_names())
        uuid = ("goal_id", _single(_UUID))
        self._types[name + "_SendGoal_Request"] = _struct(
            name + "_SendGoal_Request", uuid, ("goal", _single(name + "_Goal")))
        self._types[name + "_SendGoal_Response"] = _struct(
            name + "_SendGoal_Response",
            ("accepted", FieldType(primitive=Primitive.BOOLEAN)), ("stamp", _single(_TIME)))
        self._types[name + "_GetResult_Request"] = _struct(name + "_GetResult_Request", uuid)
        self._types[name + "_GetResult_Response"] = _struct(
            name + "_GetResult_Response",
            ("status", FieldType(primitive=Primitive.INT8)), ("result", _single(name + "_Result")))
        self._types[name + "_FeedbackMessage"] = _struct(
            name + "_FeedbackMessage", uuid, ("feedback", _single(name + "_Feedback")))
        self._derive_service(name + "_SendGoal")
        self._derive_service(name + "_GetResult")
        self._types[name] = _struct(
            name,
            ("goal", _single(name + "_Goal")),
            ("result", _single(name + "_Result")),
            ("feedback", _single(name + "_Feedback")),
            ("send_goal_service", _single(name + "_SendGoal")),
            ("get_result_service", _single(name + "_GetResult")),
            ("feedback_message", _single(name + "_FeedbackMessage")),
        )


def _interface_of(name: str) -> str:
    """The interface whose file defines `name`: `pkg/srv/S_Request` → `pkg/srv/S`."""
    pkg, kind, short = name.split("/") if name.count("/") == 2 else ("", "", name)
    suffixes = {"srv": _SERVICE_SUFFIXES, "action": _ACTION_SUFFIXES}.get(kind, ())
    for suffix in sorted(suffixes, key=len, reverse=True):
        if short.endswith(suffix):
            return f"{pkg}/{kind}/{short[: -len(suffix)]}"
    return name


def _package_dir(root: Path, pkg: str) -> Path | None:
    """Where package `pkg` is under `root`, scanned as `_scan` does."""
    if any((root / kind).is_dir() for kind in KINDS):  # a single package directory
        return root if root.name == pkg else None
    return root / pkg if (root / pkg).is_dir() else None


def _scan(root: Path) -> Iterator[tuple[str, Path]]:
    if not root.is_dir():
        return
    if any((root / kind).is_dir() for kind in KINDS):  # a single package directory
        yield from _scan_package(root.name, root)
        return
    for pkg_dir in sorted(root.iterdir()):
        if pkg_dir.is_dir() and not pkg_dir.name.startswith(("_", ".")):
            yield from _scan_package(pkg_dir.name, pkg_dir)


def _scan_package(pkg: str, pkg_dir: Path) -> Iterator[tuple[str, Path]]:
    for kind in KINDS:
        kind_dir = pkg_dir / kind
        if kind_dir.is_dir():
            for path in sorted(kind_dir.glob("*.idl")):
                yield f"{pkg}/{kind}/{path.stem}", path
