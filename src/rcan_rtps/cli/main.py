"""Entry point of `rcan-rtps`: argparse sub-commands, errors as messages, never tracebacks."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import sys
from collections.abc import Sequence

from .. import __version__, _stop_signals
from . import _logging

EXIT_ERROR = 1
EXIT_INTERRUPTED = 130
log = logging.getLogger("rcan_rtps.cli")


# Each verb's module, in the order `--help` lists them.
COMMANDS = {
    "run": "run_cmd", "topic": "topic_cmd", "node": "node_cmd", "interface": "interface_cmd",
    "config": "config_cmd", "audit": "audit_cmd", "sim": "sim_cmd", "service": "service_cmd",
    "action": "action_cmd", "discover": "discover_cmd", "bag": "bag_cmd", "param": "param_cmd",
    "doctor": "doctor_cmd", "conformance": "conformance_cmd", "mcp": "mcp_cmd",
    "security": "security_cmd",
}
# Options before the verb that take a value (the value is not a verb).
_VALUED = frozenset({"--domain-id", "--idl-path", "--distro", "--log-level", "--log-format"})


def verb_of(argv: Sequence[str]) -> str | None:
    """The command a command line names, if any (its first word that is not an option)."""
    words = iter(argv)
    for word in words:
        if word in _VALUED:
            next(words, None)
        elif not word.startswith("-"):
            return word if word in COMMANDS else None
    return None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser; with `only`, of that verb alone: a bridge run does not import (nor pay
    the memory of) the graph tools, bags and the rest of the CLI."""
    # Imported here, not at the top: until main() runs, a Ctrl-C would end in a traceback,
    # and these pull in cyclonedds, aiohttp and cryptography.
    from ._options import add_global_options

    parser = argparse.ArgumentParser(
        prog="rcan-rtps",
        description="RCAN governance for ROS 2 robots, as a plain DDS peer (no ROS needed).")
    parser.add_argument("--version", action="version", version=f"rcan-rtps {__version__}")
    add_global_options(parser)
    add_logging_options(parser)
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for verb, module in COMMANDS.items():
        if only is None or verb == only:
            importlib.import_module(f"{__package__}.{module}").register(commands)
    for command in commands_of(parser):  # global options may follow the verb too
        add_global_options(command, after_verb=True)
        add_logging_options(command, after_verb=True)
    return parser


def commands_of(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parsers that end a command line (`topic echo`, `run`), each once."""
    found: dict[int, argparse.ArgumentParser] = {}
    for action in parser._actions:  # argparse has no public walk of its sub-parsers
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                nested = commands_of(sub)
                found.update((id(p), p) for p in (nested or [sub]))
    return list(found.values())


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    from ._options import merge_global_options

    words = sys.argv[1:] if argv is None else list(argv)
    return merge_global_options(build_parser(verb_of(words)).parse_args(words))


def add_logging_options(parser: argparse.ArgumentParser, *, after_verb: bool = False) -> None:
    # After the verb: SUPPRESS defaults, so a value given before the verb is kept.
    def default(value: str | None) -> str | None:
        return argparse.SUPPRESS if after_verb else value

    parser.add_argument("--log-level", choices=_logging.LOG_LEVELS, default=default(None),
                        help="least severe level logged (default: info for `run`, which logs "
                        f"one line per decision; {_logging.DEFAULT_LOG_LEVEL} otherwise)")
    parser.add_argument("--log-format", choices=_logging.LOG_FORMATS, default=default("text"),
                        help="log lines on stderr: text (default) or json (one object a line: "
                        "time, level, logger, event, principal/audit_id where relevant, exc)")


def main(argv: Sequence[str] | None = None) -> int:
    # SIGTERM and SIGHUP (a closed terminal or ssh session) end every command as Ctrl-C does.
    with _stop_signals.stop_rules():
        return _guarded_main(argv)


def _guarded_main(argv: Sequence[str] | None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt as exc:  # before a command took the signals over (loading, parsing)
        return _interrupted(exc)
    except ImportError as exc:  # no usable cyclonedds: missing, or a line the wire refuses
        if (interrupt := caused_by_interrupt(exc)) is not None:
            return _interrupted(interrupt)
        if exc.name != "cyclonedds":
            raise
        print(f"rcan-rtps: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except Exception as exc:
        if (interrupt := caused_by_interrupt(exc)) is not None:
            return _interrupted(interrupt)
        raise


def caused_by_interrupt(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C (or other stop signal) `exc` wraps, if any. Python 3.11 wraps an exception
    raised in a class body's `__set_name__` in a RuntimeError: a Ctrl-C landing while
    cyclonedds builds its classes (at import) comes out as one."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


def _interrupted(interrupt: KeyboardInterrupt) -> int:
    print("rcan-rtps: interrupted", file=sys.stderr)
    return _stop_signals.exit_status(interrupt)


def _main(argv: Sequence[str] | None) -> int:
    args = parse_args(argv)
    _logging.configure(args.log_level or _logging.default_level(args.command),
                       args.log_format)
    from ..config import ConfigError
    from ..governance import GovernanceError
    from ..rcan import RcanError
    from ..ros.errors import WireError

    try:
        return int(args.func(args))
    except KeyboardInterrupt as exc:  # the command unwound in order (`_stop_signals.run`)
        return _stop_signals.exit_status(exc)
    except BrokenPipeError:  # `… | head`: the reader has what it wanted
        _quiet_stdout()
        return 0
    except (WireError, ConfigError, GovernanceError, RcanError, ValueError, OSError) as exc:
        report_error(exc, as_json=args.log_format == "json")
        return EXIT_ERROR


def _quiet_stdout() -> None:
    """Points stdout at /dev/null, so the interpreter's own flush at exit cannot hit the
    closed pipe again (and print a second error)."""
    import os

    with contextlib.suppress(OSError, ValueError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)


def report_error(exc: Exception, *, as_json: bool) -> None:
    # In JSON mode stderr is read by machines: the error is a log line like every other.
    if as_json:
        log.error("%s", exc)
    else:
        print(f"rcan-rtps: error: {exc}", file=sys.stderr)
