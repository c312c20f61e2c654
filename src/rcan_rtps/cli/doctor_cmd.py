"""`rcan-rtps doctor`: checks of this machine's setup for joining a ROS 2 graph, like
`ros2 doctor`, limited to what means something without ROS installed."""

from __future__ import annotations

import argparse
import os
import platform
import socket
import struct
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import ifaddr
from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsParticipant
from cyclonedds.core import DDSException

from .. import _stop_signals as stop_signals
from ..ros import qos as qos_mod
from ..ros._binding import binding_location, binding_version
from ..ros.errors import WireError
from ..ros.graph import Direction, RosGraph, node_fqn
from ..ros.participant import localhost_requested, resolve_domain_id
from ..ros.typesys.store import resolve_distro
from . import _cyclone_build as cyclone
from ._common import alone_hint, make_node, make_store

DISCOVERY_RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
SAFE_DOMAIN_IDS = range(0, 102)  # above 101, Linux's ephemeral ports may collide with DDS's
IFF_UP, IFF_LOOPBACK, IFF_MULTICAST = 0x1, 0x8, 0x1000  # from <net/if.h>
SIOCGIFFLAGS = 0x8913  # Linux


@dataclass
class Check:
    """One area checked: rows for --report, and what is questionable or wrong."""

    name: str
    title: str
    rows: list[tuple[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("doctor", help="check the setup for joining a ROS 2 graph")
    parser.add_argument("-r", "--report", action="store_true",
                        help="also print what every check found, section by section")
    parser.add_argument("--spin-time", type=float, default=2.0,
                        help="seconds to listen for other participants (default 2)")
    parser.set_defaults(func=lambda a: stop_signals.run(_doctor(a)))


async def _doctor(args: argparse.Namespace) -> int:
    library = cyclone.c_library()
    checks = [_platform(), _middleware(library), _security(library), _environment(args),
              _network(args), _interfaces(args), await _graph(args)]
    if args.report:
        for check in checks:
            print(_section(check))
    for check in checks:
        for warning in check.warnings:
            print(f"WARNING ({check.name}): {warning}")
        for error in check.errors:
            print(f"ERROR ({check.name}): {error}")
    failed = [c.name for c in checks if c.errors]
    if failed:
        print(f"{len(failed)}/{len(checks)} check(s) failed\nFailed modules: {' '.join(failed)}")
        return 1
    print(f"All {len(checks)} checks passed")
    return 0


def _section(check: Check) -> str:
    width = max((len(key) for key, _ in check.rows), default=0)
    lines = [f"\n   {check.title}"] + [f"{key:<{width}} : {value}" for key, value in check.rows]
    return "\n".join(lines)


def _platform() -> Check:
    check = Check("platform", "PLATFORM INFORMATION")
    uname = platform.uname()
    libc = " ".join(filter(None, platform.libc_ver()))
    check.rows = [("system", uname.system), ("platform info", platform.platform()),
                  ("release", uname.release), ("processor", uname.machine or "unknown"),
                  ("python", f"{platform.python_implementation()} {platform.python_version()}"
                   f" ({sys.executable})"),
                  ("libc", libc or "unknown")]
    return check


def _middleware(library: cyclone.CLibrary) -> Check:
    check = Check("middleware", "RMW MIDDLEWARE")
    version = binding_version()
    if version == "unknown":
        check.warnings.append("the cyclonedds distribution has no metadata; is it installed "
                              "with pip?")
    where = f"{library.path} ({library.origin})" if library.path else library.origin
    options = cyclone.build_options(library)
    uri = os.environ.get("CYCLONEDDS_URI", "").strip()
    check.rows = [("middleware name", "cyclonedds (Python binding)"),
                  ("cyclonedds version", f"{version} ({binding_location()})"),
                  ("Cyclone DDS C library", f"{library.version} at {where}"),
                  ("C build options", ", ".join(f"{name}: {'yes' if on else 'no'}"
                                                for name, on in options.items())),
                  ("equivalent rmw", "rmw_cyclonedds_cpp (interoperates with any rmw over DDS)"),
                  ("CYCLONEDDS_URI", uri or "(not set)")]
    if library.version not in ("unknown", version):
        check.warnings.append(f"the binding is {version} but its C library is "
                              f"{library.version}: build both from the same release")
    for path in _config_files(uri):
        if not path.is_file():
            check.errors.append(f"CYCLONEDDS_URI names {path}, which is not a file")
    return check


def _security(library: cyclone.CLibrary) -> Check:
    """DDS-Security (what SROS2 runs on): built into libddsc, and its three plugins
    loadable; and what ROS_SECURITY_* ask for."""
    check = Check("security", "DDS SECURITY")
    built_in = cyclone.build_options(library)["DDS-Security"]
    plugins = cyclone.security_plugins(library)
    check.rows.append(("built into the C library", "yes" if built_in else
                       "no (PyPI's cyclonedds wheel is built without it)"))
    for plugin in plugins:
        check.rows.append((f"plugin {plugin.name}", _plugin_state(plugin)))
    available = built_in and all(p.loadable for p in plugins)
    check.rows.append(("available", "yes" if available else "no"))
    env = os.environ
    enable = env.get("ROS_SECURITY_ENABLE", "")
    strategy = env.get("ROS_SECURITY_STRATEGY", "")
    check.rows += [("ROS_SECURITY_ENABLE", enable or "(not set)"),
                   ("ROS_SECURITY_STRATEGY", strategy or "(not set: Permissive)"),
                   ("ROS_SECURITY_KEYSTORE", env.get("ROS_SECURITY_KEYSTORE", "") or "(not set)")]
    if enable.lower() == "true" and not available:
        problem = ("ROS_SECURITY_ENABLE=true but this Cyclone DDS cannot do DDS-Security: "
                   "use a Cyclone DDS C 11 built with security (CYCLONEDDS_HOME) and its "
                   "binding built against it")
        (check.errors if strategy == "Enforce" else check.warnings).append(problem)
    return check


def _plugin_state(plugin: cyclone.Plugin) -> str:
    if plugin.on_search_path:
        return "loadable (on the library path)"
    if plugin.found and plugin.loadable:
        return (f"at {plugin.found}, not on the library path (add its directory to "
                "LD_LIBRARY_PATH, or name the file in the security settings)")
    if plugin.found:
        return f"at {plugin.found}, does not load"
    return "not found"


def _config_files(uri: str) -> Iterator[Path]:
    """The files CYCLONEDDS_URI refers to (it may also hold inline XML, not checked here)."""
    for part in filter(None, (p.strip() for p in uri.split(","))):
        if part.startswith("file://"):
            yield Path(part.removeprefix("file://"))
        elif not part.startswith("<"):
            yield Path(part)


def _environment(args: argparse.Namespace) -> Check:
    check = Check("environment", "ROS 2 ENVIRONMENT")
    env = os.environ
    _check_domain(check, args.domain_id)
    _check_discovery_range(check, env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", ""),
                           env.get("ROS_LOCALHOST_ONLY", ""))
    check.rows.append(("ROS_STATIC_PEERS", env.get("ROS_STATIC_PEERS", "") or "(not set)"))
    if env.get("ROS_STATIC_PEERS", "").strip():
        check.warnings.append("ROS_STATIC_PEERS is not used by rcan-rtps; list peers in a "
                              "CYCLONEDDS_URI <Peers> element instead")
    try:
        distro = resolve_distro(args.distro)
        check.rows.append(("distribution", f"{distro} (ROS_DISTRO={env.get('ROS_DISTRO', '')!r})"))
    except WireError as exc:
        check.errors.append(str(exc))
    return check


def _check_domain(check: Check, explicit: int | None) -> None:
    try:
        domain = resolve_domain_id(explicit)
    except WireError as exc:
        check.errors.append(str(exc))
        return
    if explicit is not None:
        source = "from --domain-id"
    elif os.environ.get("ROS_DOMAIN_ID", "").strip():
        source = "from the environment"
    else:
        source = "ROS_DOMAIN_ID is not set: the default"
    check.rows.append(("ROS_DOMAIN_ID", f"{domain} ({source})"))
    if domain not in SAFE_DOMAIN_IDS:
        check.warnings.append(f"domain id {domain} is above 101: on Linux its ports can collide "
                              "with ephemeral ports")


def _check_discovery_range(check: Check, scope: str, localhost_only: str) -> None:
    check.rows += [("ROS_AUTOMATIC_DISCOVERY_RANGE", scope or "(not set: SUBNET)"),
                   ("ROS_LOCALHOST_ONLY", localhost_only or "(not set)")]
    if scope and scope.upper() not in DISCOVERY_RANGES:
        check.errors.append(f"ROS_AUTOMATIC_DISCOVERY_RANGE={scope!r} is not one of "
                            f"{', '.join(DISCOVERY_RANGES)}")
    elif scope.upper() == "OFF":
        check.warnings.append("ROS_AUTOMATIC_DISCOVERY_RANGE=OFF is not supported by rcan-rtps: "
                              "it discovers peers on the subnet")
    if localhost_only and localhost_only not in ("0", "1"):
        check.errors.append(f"ROS_LOCALHOST_ONLY={localhost_only!r} is neither 0 nor 1")
    elif localhost_only:
        check.warnings.append("ROS_LOCALHOST_ONLY is deprecated since Jazzy; use "
                              "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST")


def _network(args: argparse.Namespace) -> Check:
    check = Check("network", "NETWORK CONFIGURATION")
    usable = []
    for adapter in ifaddr.get_adapters():
        flags = _interface_flags(adapter.name)
        addresses = [ip.ip for ip in adapter.ips if isinstance(ip.ip, str)]
        check.rows.append((adapter.nice_name, f"{', '.join(addresses) or '(no IPv4)'} "
                           f"[{_describe_flags(flags)}]"))
        if addresses and (flags is None or flags & IFF_UP):
            usable.append((adapter.nice_name, flags))
    if not usable:
        check.errors.append("no network interface with an IPv4 address is up")
        return check
    multicast = [(name, flags) for name, flags in usable
                 if flags is None or flags & IFF_MULTICAST]
    check.rows.append(("discovery", _discovery_scope(args.localhost)))
    if localhost_requested(args.localhost):
        return check  # loopback unicast: no multicast needed
    if not multicast:
        check.warnings.append("no interface that is up has multicast: DDS discovery finds no "
                              "peer unless --localhost or CYCLONEDDS_URI <Peers> is used")
    elif all(flags is not None and flags & IFF_LOOPBACK for _, flags in multicast):
        check.warnings.append("only loopback is up with multicast: DDS discovery will find "
                              "peers on this machine only")
    return check


def _discovery_scope(explicit: bool | None) -> str:
    if not localhost_requested(explicit):
        return "the subnet (multicast on the interfaces that have it)"
    if explicit:
        source = "--localhost"
    elif os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").upper() == "LOCALHOST":
        source = "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST"
    else:
        source = "ROS_LOCALHOST_ONLY=1"
    return f"this machine only, unicast over loopback (from {source})"


def _interface_flags(name: str) -> int | None:
    """IFF_* flags of an interface (None where unknown). Asked of the kernel with
    SIOCGIFFLAGS, not read from sysfs: that shows the flags of the namespace /sys was
    mounted in, not of this process's network namespace."""
    try:
        import fcntl  # POSIX only
    except ImportError:
        return None
    request = struct.pack("16sH", name.encode()[:15], 0)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            answer = fcntl.ioctl(sock.fileno(), SIOCGIFFLAGS, request)
    except OSError:
        return None
    return int(struct.unpack("16sH", answer[:18])[1])


def _describe_flags(flags: int | None) -> str:
    if flags is None:
        return "flags unknown"
    named = [("up" if flags & IFF_UP else "down"),
             *(["loopback"] if flags & IFF_LOOPBACK else []),
             ("multicast" if flags & IFF_MULTICAST else "no multicast")]
    return ", ".join(named)


def _interfaces(args: argparse.Namespace) -> Check:
    check = Check("interfaces", "INTERFACE DEFINITIONS")
    try:
        store = make_store(args)
        names = store.interface_names()
        for core in ("std_msgs/msg/Header", "rcl_interfaces/srv/GetParameters",
                     "rmw_dds_common/msg/ParticipantEntitiesInfo"):
            store.hash_of(core)
    except (WireError, OSError) as exc:
        check.errors.append(f"the IDL bundle does not load: {exc}")
        return check
    packages = {name.split("/")[0] for name in names}
    check.rows = [("interfaces", f"{len(names)} in {len(packages)} packages"),
                  ("core types", "std_msgs, rcl_interfaces, rmw_dds_common load and hash")]
    return check


async def _graph(args: argparse.Namespace) -> Check:
    check = Check("graph", "ROS 2 GRAPH")
    try:
        node = make_node(args)
    except (WireError, DDSException, OSError) as exc:
        check.errors.append(f"cannot join the DDS domain: {exc}")
        return check
    with node:
        participants = BuiltinDataReader(node.participant, BuiltinTopicDcpsParticipant)
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        own = node.participant.guid
        others = {s.key for s in participants.take(N=10_000) if s.key != own}
        nodes = [(ns, name) for ns, name in graph.nodes() if name != node.name]
        check.rows = [("domain", str(node.domain_id)),
                      ("other participants", str(len(others))),
                      ("nodes", ", ".join(node_fqn(ns, n) for ns, n in nodes) or "none")]
        hint = alone_hint(args, node, graph)
        if not others:
            check.warnings.append(hint or f"no other participant on ROS domain "
                                  f"{node.domain_id}")
        _check_topics(check, graph)
    return check


def _check_topics(check: Check, graph: RosGraph) -> None:
    """Like ros2 doctor: publishers nobody listens to, and pairs whose QoS never match."""
    for topic in graph.topics(include_hidden=False):
        endpoints = graph.topic_endpoints(topic)
        pubs = [e for e in endpoints if e.direction is Direction.PUBLISHER]
        subs = [e for e in endpoints if e.direction is Direction.SUBSCRIPTION]
        check.rows.append((f"topic {topic}", f"{len(pubs)} publisher(s), "
                           f"{len(subs)} subscription(s)"))
        if pubs and not subs:
            check.warnings.append(f"publisher without subscription on {topic}")
        for pub in pubs:
            for sub in subs:
                for problem in qos_mod.incompatibilities(pub.qos, sub.qos):
                    check.warnings.append(f"{topic}: {node_fqn(pub.node_namespace, pub.node_name)}"
                                          f" → {node_fqn(sub.node_namespace, sub.node_name)}: "
                                          f"{problem}")
