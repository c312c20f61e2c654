"""Errors of the ROS 2 wire layer.

    WireError
    ├── UnsupportedBindingError the installed cyclonedds cannot run the wire layer (at import;
    │                           also an ImportError)
    ├── IdlSyntaxError          an .idl file does not parse (file and line)
    ├── UnknownTypeError        a type name the store does not hold (with near names)
    ├── UnsupportedTypeError    a type the cyclonedds codec cannot carry (wstring, wchar, ...)
    ├── UnsupportedDistroError  a ROS distro the IDL bundle does not cover (also a ValueError)
    ├── ValueFitError           a value does not fit its type (with the field path)
    ├── CdrDecodeError          bytes that do not decode as the type they were said to be
    ├── SampleTooLarge          a sample past the domain's size bound (`max_sample_bytes`)
    ├── InvalidNameError        a ROS name breaks a validity rule (the rule is named)
    ├── QosError                a QoS profile that cannot be built or cannot match
    ├── GraphTimeout            something did not appear on the graph in time
    ├── ServiceUnavailable      no server for a service (or action) within the timeout
    ├── ServiceTimeout          a server was there but no reply came in time
    └── ActionError             an action goal could not be sent, confirmed or followed

Misuse (an API called out of order) raises RuntimeError/TypeError as Python does.
"""

from __future__ import annotations

from collections.abc import Iterable


def seconds(duration: float) -> str:
    """A duration for people: `1 s`, `0.5 s`, `2.5 s` (timeouts left over from a deadline
    come as 0.999997)."""
    text = f"{duration:.1f}".rstrip("0").rstrip(".") if duration < 10 else f"{duration:.0f}"
    return f"{text} s"


class WireError(Exception):
    """Base of every error raised by `rcan_rtps.ros`."""


class UnsupportedBindingError(WireError, ImportError):
    """The installed cyclonedds binding lacks what the wire layer calls (the 0.10 line).

    Raised when `rcan_rtps.ros` is imported, so an ImportError too: `name` is 'cyclonedds'.
    The message names the version found, what is missing and how to get the 11.x line."""

    def __init__(self, version: str, location: str, missing: list[str]) -> None:
        lines = [
            f"the cyclonedds Python binding {version} (at {location}) cannot run rcan-rtps, "
            "which needs its 11.x line; it lacks:",
            *(f"  - {item}" for item in missing),
            "Install the 11.x line into this environment: pip install 'cyclonedds>=11,<12' "
            "(wheels for Linux x86_64 and macOS).",
            "Where no wheel exists (Linux aarch64): scripts/install-aarch64.sh in a source "
            "checkout does it all (docs/aarch64.md); by hand, build Cyclone DDS C 11 from its "
            "release source (cmake, Release), run ldconfig for its lib directory, then "
            "CYCLONEDDS_HOME=<its install prefix> pip install 'cyclonedds>=11,<12'.",
            "Debian's and Ubuntu's python3-cyclonedds and cyclonedds-dev are the 0.10 line; "
            "see docs/compatibility.md ('Cyclone DDS lines').",
        ]
        super().__init__("\n".join(lines), name="cyclonedds")
        self.version = version
        self.location = location
        self.missing = list(missing)


class IdlSyntaxError(WireError):
    def __init__(self, path: str, line: int, message: str) -> None:
        super().__init__(f"{path}:{line}: {message}")
        self.path = path
        self.line = line
        self.detail = message


class UnknownTypeError(WireError):
    def __init__(self, name: str, known: Iterable[str] = ()) -> None:
        import difflib  # here: an error's hint, not worth its memory in a process that runs

        known = list(known)
        near = difflib.get_close_matches(name, known, n=3, cutoff=0.6)
        if not near:
            short = name.rsplit("/", 1)[-1].lower()
            near = [k for k in known if k.rsplit("/", 1)[-1].lower() == short][:3]
        hints = [f"did you mean {', '.join(near)}?"] if near else []
        package = name.split("/", 1)[0]
        if not any(k.split("/", 1)[0] == package for k in known):  # a typo cannot be all
            hints.insert(0, f"package {package!r} is not in the bundled IDL: add a ROS "
                         "install's IDL with `--idl-path <ros>/share` (e.g. "
                         "/opt/ros/jazzy/share; also RCAN_RTPS_IDL_PATH)")
        super().__init__(f"unknown type {name!r}" + "".join(f"; {h}" for h in hints))
        self.name = name
        self.suggestions = near


class UnsupportedTypeError(WireError):
    """A type the cyclonedds codec cannot carry (wchar, long double)."""


class UnsupportedDistroError(WireError, ValueError):
    # ValueError too: callers of `resolve_distro` caught ValueError before this class existed.
    pass


class ValueFitError(WireError):
    def __init__(self, path: str, message: str) -> None:
        where = path or "<message>"
        super().__init__(f"{where}: {message}")
        self.path = path
        self.detail = message


class CdrDecodeError(WireError):
    """Bytes that are not the CDR of the type named (truncated, wrong type, no header)."""


class SampleTooLarge(WireError):
    """A sample past the domain's bound on sample size (`RosNode(max_sample_bytes=)`):
    Cyclone sends none such, nor takes one in."""


class InvalidNameError(WireError):
    def __init__(self, name: str, rule: str, index: int | None = None) -> None:
        at = f" (at index {index})" if index is not None else ""
        super().__init__(f"invalid ROS name {name!r}: {rule}{at}")
        self.name = name
        self.rule = rule
        self.index = index


class QosError(WireError):
    pass


class GraphTimeout(WireError):
    pass


class ServiceUnavailable(WireError):
    pass


class ServiceTimeout(WireError):
    pass


class AmbiguousReply(WireError):
    """A reply came that cannot be told from another client's: the server names the request
    a reply answers only in RTPS inline QoS, unreadable here, and another client of the
    service may be calling it. Never taken as ours (a wrong answer delivered as a right one
    is worse than none); the call may be made again."""

    code = "ambiguous_reply"


class ActionError(WireError):
    pass
