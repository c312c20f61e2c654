"""`rcan-rtps interface list|show|hash`: the IDL bundle and extra IDL paths."""

from __future__ import annotations

import argparse

from ..ros.errors import UnknownTypeError
from ..ros.typesys.model import MessageType
from ..ros.typesys.store import TypeStore, normalize_name
from ._common import make_store

EMPTY_PLACEHOLDER = "structure_needs_at_least_one_member"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("interface", help="list and show message types")
    actions = parser.add_subparsers(dest="interface_command", required=True)
    listing = actions.add_parser("list", help="every known interface")
    for flag, kind in (("-m", "messages"), ("-s", "services"), ("-a", "actions")):
        listing.add_argument(flag, f"--only-{kind}", dest=kind, action="store_true",
                             help=f"list {kind} (combinable; default: all kinds)")
    listing.set_defaults(func=list_command)
    packages = actions.add_parser("packages", help="packages with interfaces")
    packages.set_defaults(func=packages_command)
    show = actions.add_parser("show", help="fields and constants of a type")
    show.add_argument("type", metavar="TYPE", help="e.g. sensor_msgs/msg/JointState")
    show.set_defaults(func=show_command)
    hashing = actions.add_parser("hash", help="the RIHS01 type hash of a type")
    hashing.add_argument("type", metavar="TYPE", help="e.g. geometry_msgs/msg/Twist")
    hashing.set_defaults(func=hash_command)


def list_command(args: argparse.Namespace) -> int:
    names = make_store(args).interface_names()
    wanted = {k for k, flag in (("msg", args.messages), ("srv", args.services),
                                ("action", args.actions)) if flag} or {"msg", "srv", "action"}
    titles = {"msg": "Messages", "srv": "Services", "action": "Actions"}
    for kind in ("msg", "srv", "action"):
        if kind in wanted:
            print(f"{titles[kind]}:")
            for name in names:
                if name.split("/")[1] == kind:
                    print(f"    {name}")
    return 0


def packages_command(args: argparse.Namespace) -> int:
    for package in sorted({name.split("/")[0] for name in make_store(args).interface_names()}):
        print(package)
    return 0


def _describe(store: TypeStore, msg: MessageType, indent: str = "") -> list[str]:
    lines = [f"{indent}{c.type.ros_spelling()} {c.name}={c.value!r}" for c in msg.constants]
    for f in msg.fields:
        if f.name == EMPTY_PLACEHOLDER and len(msg.fields) == 1:
            continue  # rosidl's stand-in for "no fields" (an empty request, say)
        default = f" {f.default!r}" if f.default is not None else ""
        lines.append(f"{indent}{f.type.ros_spelling()} {f.name}{default}")
        if f.type.nested is not None:
            lines.extend(_describe(store, store.message(f.type.nested), indent + "\t"))
    return lines


KINDS = ("msg", "srv", "action")


def _interface(store: TypeStore, given: str) -> str:
    """`given` as the full name of an interface: `pkg/T` is the message `pkg/msg/T`, or else
    the one service or action of that name (`std_srvs/Trigger`)."""
    parts = given.strip("/").split("/")
    if len(parts) == 2 and parts[1] in KINDS:  # a package's kind, not a type
        raise UnknownTypeError(given, [n for n in store.interface_names()
                                       if n.startswith(f"{parts[0]}/{parts[1]}/")])
    name = normalize_name(given)
    if len(parts) != 2 or name in store.interface_names():
        return name
    found = [f"{parts[0]}/{kind}/{parts[1]}" for kind in KINDS
             if f"{parts[0]}/{kind}/{parts[1]}" in store.interface_names()]
    return found[0] if len(found) == 1 else name


def show_command(args: argparse.Namespace) -> int:
    store = make_store(args)
    name = _interface(store, args.type)
    kind = name.split("/")[1] if name.count("/") == 2 else "msg"
    if kind == "srv" and name in store.interface_names():
        svc = store.service(name)
        parts = [svc.request, svc.response]
    elif kind == "action" and name in store.interface_names():
        act = store.action(name)
        parts = [act.goal, act.result, act.feedback]
    else:
        parts = [store.message(name)]
    lines: list[str] = []
    for index, part in enumerate(parts):
        lines.extend(["---"] if index else [])
        lines.extend(_describe(store, part))
    print("\n".join(lines))
    return 0


def hash_command(args: argparse.Namespace) -> int:
    print(make_store(args).hash_of(args.type))
    return 0
