"""`rcan-rtps param` against a node whose parameter services answer what no rclpy node does.

Any participant may serve `<node>/get_parameters` and `list_parameters` and answer what it
likes (red team 32). The node here is real DDS: a participant of ours serving the
rcl_interfaces services with the answers a broken or hostile node gives. The command must
end with a clear error or a faithful answer: never a traceback, a value shown under another
name, or an escape sequence for the operator's terminal.
"""

from __future__ import annotations

import asyncio
import subprocess
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from rcan_rtps.ros.participant import RosNode
from rcan_rtps.ros.service_server import ServiceServer

from .test_cli_param_node import cli

NODE = "/demo/strange"
HOSTILE = "\x1b]0;owned\x07\x1b[2J"

Answers = dict[str, Callable[[Any], dict[str, Any]]]


@pytest.fixture
async def strange(domain_id: int, jazzy_share: Path) -> AsyncIterator[Answers]:
    """A node serving list_parameters and get_parameters with what the test puts in the
    returned dict (a function of the request, per service)."""
    answers: Answers = {}
    with RosNode("strange", "/demo", domain_id=domain_id, distro="jazzy",
                 idl_paths=[jazzy_share]) as node:
        servers = []
        for service, kind in (("list_parameters", "ListParameters"),
                              ("get_parameters", "GetParameters")):
            async def handler(request: Any, service: str = service) -> dict[str, Any]:
                return answers[service](request)
            servers.append(ServiceServer(node, f"{NODE}/{service}",
                                         f"rcl_interfaces/srv/{kind}", handler))
        yield answers
        await asyncio.gather(*(s.close() for s in servers))


async def run_cli(domain_id: int, *args: str) -> subprocess.CompletedProcess[str]:
    return await asyncio.to_thread(cli, domain_id, "param", *args, "--timeout", "20")


def assert_no_traceback(done: subprocess.CompletedProcess[str]) -> None:
    assert "Traceback" not in done.stderr, done.stderr


async def test_a_type_parameter_type_does_not_define_is_an_error(
        strange: Answers, domain_id: int) -> None:
    """`param get` of a value typed 42 raised KeyError out of the command (a traceback)."""
    strange["get_parameters"] = lambda request: {"values": [{"type": 42, "integer_value": 7}]}
    got = await run_cli(domain_id, "get", NODE, "speed")
    assert_no_traceback(got)
    assert got.returncode == 1
    assert "type 42" in got.stderr and NODE in got.stderr and "speed" in got.stderr


async def test_values_not_one_per_name_are_an_error(strange: Answers, domain_id: int) -> None:
    """`param dump` paired names and values with zip: a reply short of a value left
    parameters out of the dump unsaid (one of another order would show values under the
    wrong names)."""
    strange["list_parameters"] = lambda request: {
        "result": {"names": ["a", "b", "c"], "prefixes": []}}
    strange["get_parameters"] = lambda request: {"values": [
        {"type": 2, "integer_value": 1}, {"type": 2, "integer_value": 2}]}
    dump = await run_cli(domain_id, "dump", NODE)
    assert_no_traceback(dump)
    assert dump.returncode == 1 and dump.stdout == ""
    assert "2 value(s) for the 3 parameter(s)" in dump.stderr


async def test_a_name_below_another_parameter_is_dumped_dotted(
        strange: Answers, domain_id: int) -> None:
    """A node may declare both `a` and `a.b`: `param dump` nested `a.b` into `a`'s value
    (TypeError: 'int' object does not support item assignment, a traceback)."""
    values = {"a": 1, "a.b": 2, "a.b.c": 3, "x.y": 4}
    strange["list_parameters"] = lambda request: {
        "result": {"names": list(values), "prefixes": []}}
    strange["get_parameters"] = lambda request: {"values": [
        {"type": 2, "integer_value": values[n]} for n in request.names]}
    dump = await run_cli(domain_id, "dump", NODE)
    assert_no_traceback(dump)
    assert dump.returncode == 0, dump.stderr
    params = yaml.safe_load(dump.stdout)[NODE]["ros__parameters"]
    assert params == {"a": 1, "a.b": 2, "a.b.c": 3, "x": {"y": 4}}


async def test_names_and_values_are_shown_not_obeyed(strange: Answers, domain_id: int) -> None:
    """`param list` and `param get` printed a node's parameter names and string values as
    they came: any participant serving them could send the operator's terminal escape
    sequences (retitle it, clear it), as red team 19 found of `discover`."""
    strange["list_parameters"] = lambda request: {
        "result": {"names": [f"evil{HOSTILE}"], "prefixes": []}}
    strange["get_parameters"] = lambda request: {"values": [
        {"type": 4, "string_value": f"value{HOSTILE}"}]}
    listing = await run_cli(domain_id, "list", NODE)
    got = await run_cli(domain_id, "get", NODE, "evil")
    for done in (listing, got):
        assert done.returncode == 0, done.stderr
        assert "\x1b" not in done.stdout and "\\x1b]0;owned\\x07" in done.stdout
