"""A bridge run imports what serving needs, not the rest of the CLI (issue 14: idle memory).

The set comes from the running process itself (`PYTHONPROFILEIMPORTTIME`: one stderr line per
module imported), up to and after its ready line and a governed command; no timing or memory
figure is asserted, only which modules were loaded.
"""

from __future__ import annotations

import contextlib
import json
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from rcan_rtps.cli.main import COMMANDS
from rcan_rtps.governance.audit import load_or_create_key
from rcan_rtps.ros import ActionServer, ServerGoal, ServiceServer

from .run_process import RunProcess, child_env, state_args

EXIT_TIMEOUT = 60.0
# Loaded only by the commands, options or requests that use them.
NOT_FOR_A_RUN = {
    *(f"rcan_rtps.cli.{module}" for module in COMMANDS.values() if module != "run_cmd"),
    "rcan_rtps.cli._common", "rcan_rtps.cli._echo", "rcan_rtps.cli._measure",
    "rcan_rtps.ros.bag", "mcap",  # bags
    "rcan_rtps.bridge.mdns", "zeroconf",  # --no-mdns
    "prometheus_client",  # until /api/metrics is scraped
    "concurrent.futures.process", "multiprocessing",  # until an audit verification
    # a key is written (first start) and parsed (later ones) without it
    "cryptography.hazmat.primitives.serialization",
    "rcan_rtps.api._openapi",  # until /api/openapi.json is asked for
    "difflib",  # "did you mean" hints of config and type errors
    "rcan_rtps.mcp_server", "mcp", "mcp_types",  # `rcan-rtps mcp` (the `mcp` extra)
    # issue 27 (idle footprint): loaded by the first request that needs them
    "rcan_rtps.api._asgi", "rcan_rtps.api._local",  # /mcp
    "rcan_rtps.api._safety_manifest",  # /api/safety/manifest, /mcp
    "rcan_rtps.api._audit_export", "csv",  # /api/v1/audit
    "importlib.resources", "zipfile",  # the console's files (/console/)
    "cryptography.hazmat.primitives.asymmetric.mldsa",  # a principal's ML-DSA key
    "pkgutil",  # the action registry lists its folder itself
    "encodings.idna", "stringprep",  # the API's address is resolved as bytes
    "rcan_rtps.governance.logcheck",  # GET /api/audit/verify's worker process
    "rcan_rtps.api._ws",  # GET /api/ws
    "rcan_rtps.api._mcp",  # /mcp (McpDoor)
    "rcan_rtps.api._console_pages", "rcan_rtps.console",  # the console and its API calls
    "rcan_rtps.api._invoke",  # INVOKE, INVOKE_CANCEL, AUTHORIZE, GET /api/skills
    "rcan_rtps.governance.thoughts",  # an AI command, GET /api/thoughts/{id}
    "rcan_rtps.governance.jwt",  # bridge.api.jwt
    "rcan_rtps.api._reads",  # GET /api/audit, /api/audit/mine, /api/audit/verify
    # HiTL review, audit reads, images, thoughts, skills (api._app.RARE_ROUTES)
    "rcan_rtps.api._rare_routes",
}


# Each lazily loaded door, the request that opens it and the modules that request loads.
FIRST_USE = {
    "/console/": {"rcan_rtps.api._console_pages", "rcan_rtps.console"},
    "/api/whoami": {"rcan_rtps.api._console_pages"},
    "/api/skills": {"rcan_rtps.api._invoke", "rcan_rtps.api._rare_routes"},
    "/api/thoughts/no-such-thought": {"rcan_rtps.governance.thoughts"},
    "/api/audit/mine?last=5": {"rcan_rtps.api._reads"},
    "/api/hitl/pending?mine=true": set(),
    "/api/images": set(),
}


def imported(stderr: list[str]) -> set[str]:
    found = (re.match(r"import time:\s+\d+ \|\s+\d+ \|\s*(\S+)", line) for line in stderr)
    return {m.group(1) for m in found if m}


def get(url: str, token: str) -> tuple[int, bytes]:
    request = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=30) as reply:
            return int(reply.status), reply.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def command(url: str, token: str) -> int:
    return post(url, token, {"action": "move", "params": {"linear_x": 0.1, "duration_s": 0.2}})[0]


def post(url: str, token: str, body: dict[str, object]) -> tuple[int, dict[str, object]]:
    request = urllib.request.Request(
        f"{url}/api/command", data=json.dumps(body).encode(), method="POST",
        headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=60) as reply:
            return int(reply.status), json.loads(reply.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read())


@pytest.mark.parametrize("start", ["first", "later"])
def test_a_bridge_run_leaves_cli_only_modules_unimported(tmp_path: Path, domain_id: int,
                                                          start: str) -> None:
    # A first start writes the audit key; a later one reads it.
    (tmp_path / "state").mkdir(mode=0o700)
    if start == "later":
        load_or_create_key(tmp_path / "state" / "audit-ed25519.key")
    env = child_env(domain_id, PYTHONPROFILEIMPORTTIME="1")
    proc = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")], env, demo=True)
    try:
        assert command(proc.url, proc.user) == 200, proc.output()
        proc.signal(signal.SIGINT)
        assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
        modules = imported(proc.stderr)
        assert "rcan_rtps.bridge.runtime" in modules  # the import log is complete
        assert (tmp_path / "state" / "audit-ed25519.key").exists()  # made or read
        loaded = {m for m in NOT_FOR_A_RUN
                  if m in modules or any(n.startswith(m + ".") for n in modules)}
        assert not loaded, f"a bridge run imported {sorted(loaded)}"
    finally:
        proc.kill()


def test_the_lazy_doors_answer_their_first_request(tmp_path: Path, domain_id: int) -> None:
    """What a run leaves unimported is loaded by the first request that needs it, and that
    request is answered as it would have been (issue 27)."""
    env = child_env(domain_id, PYTHONPROFILEIMPORTTIME="1")
    proc = RunProcess(["run", "--sim", "--port", "0", "--no-mdns",
                       *state_args(tmp_path, "state")], env, demo=True)
    try:
        answers = {path: get(proc.url + path, proc.user) for path in FIRST_USE}
        proc.signal(signal.SIGINT)
        assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
    finally:
        proc.kill()
    status, page = answers["/console/"]
    assert status == 200 and b"<html" in page.lower(), answers
    status, who = answers["/api/whoami"]
    assert status == 200 and json.loads(who)["principal"] == "operator", answers
    status, skills = answers["/api/skills"]
    assert status == 200 and "invoke" in json.loads(skills)["caps"], answers
    status, mine = answers["/api/audit/mine?last=5"]
    assert status == 200 and json.loads(mine)["entries"] == [], answers  # commanded nothing
    status, thought = answers["/api/thoughts/no-such-thought"]
    assert status == 404 and json.loads(thought)["reason"] == "thought_not_found", answers
    status, pending = answers["/api/hitl/pending?mine=true"]
    assert status == 200 and json.loads(pending)["pending"] == [], answers
    status, images = answers["/api/images"]
    assert status == 200 and "images" in json.loads(images), answers
    modules = imported(proc.stderr)
    missing = {m for needed in FIRST_USE.values() for m in needed} - modules
    assert not missing, f"first requests answered without loading {sorted(missing)}"


# What only a goal action client needs (issue 27, item 6): loaded at start when the config
# names a goal server (the stop path cancels its goals: no import may wait there), never when
# it names none.
GOAL_CLIENT = {"rcan_rtps.bridge.navigation", "rcan_rtps.ros.actions", "rcan_rtps.ros.services",
               "rcan_rtps.ros.handshake", "rcan_rtps.ros._cyclone_header"}
# The goal-sending side of an action client (issue 27, item 6): no stop needs it, so a run
# loads it with its first goal (`navigate`, `dock`), never at start.
GOAL_SENDING = {"rcan_rtps.ros.action_goals", "rcan_rtps.bridge.sent_goals"}
# The server sides of actions and services: a bridge sends goals and calls services, it never
# serves one (only `--sim`'s robot does), so no run of it loads them (issue 27, item 6).
SERVER_SIDE = {"rcan_rtps.ros.action_server", "rcan_rtps.ros.service_server"}
TOKEN = "run-imports-token-0123456789abcdef"
NO_GOAL_SERVERS = ", nav_action: null, dock_action: null"


def config_run(tmp_path: Path, domain_id: int, ros2_extra: str = "") -> RunProcess:
    """`run --config` of a robot on /robot1 (no --sim: the simulator serves goals itself)."""
    config = idle_config(tmp_path, domain_id, ros2_extra)
    env = child_env(domain_id, PYTHONPROFILEIMPORTTIME="1", RCAN_BRIDGE_TOKEN=TOKEN)
    return RunProcess(["run", "--config", str(config), "--port", "0", "--no-mdns"], env,
                      demo=False)


def start_and_serving(proc: RunProcess) -> tuple[set[str], set[str]]:
    """Of an ended run: the modules imported before the bridge said it runs (its last line
    before the ready line), and those imported while it served, up to its shutdown."""
    lines = list(proc.stderr)
    running = next(i for i, line in enumerate(lines) if "bridge running" in line)
    stopping = next(i for i, line in enumerate(lines) if "shutting down" in line)
    return imported(lines[:running]), imported(lines[running:stopping])


@contextlib.contextmanager
def sim_robot(domain_id: int) -> Iterator[None]:
    """`rcan-rtps sim` on /robot1, in a process of its own: a robot with both goal servers."""
    sim = subprocess.Popen([sys.executable, "-m", "rcan_rtps", "sim", "--namespace", "/robot1"],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                           env=child_env(domain_id), start_new_session=True)
    try:
        assert sim.stdout is not None and "sim ready" in sim.stdout.readline()
        yield
    finally:
        sim.terminate()
        sim.wait(30)


def test_a_bridge_naming_no_goal_server_loads_no_action_client(tmp_path: Path,
                                                               domain_id: int) -> None:
    with sim_robot(domain_id):
        proc = config_run(tmp_path, domain_id, NO_GOAL_SERVERS)
        try:
            stopped = post(proc.url, TOKEN, {"action": "stop"})
            navigated = post(proc.url, TOKEN, {"action": "navigate",
                                               "params": {"x": 1.0, "y": 0.0, "yaw": 0.0}})
            proc.signal(signal.SIGINT)
            assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
        finally:
            proc.kill()
    assert stopped[0] == 200, (stopped, proc.output())
    # Refused, though the robot serves it: the config names no NavigateToPose server.
    assert navigated[0] != 200 and "NavigateToPose is not available" in json.dumps(navigated), \
        navigated
    modules = imported(proc.stderr)
    assert "rcan_rtps.bridge.goals" in modules  # the import log is complete
    assert not GOAL_CLIENT & modules, f"imported {sorted(GOAL_CLIENT & modules)}"


def outcome_lines(lines: list[str], action: str) -> list[int]:
    """Where the run logged the outcome of each `action` command (its audit entry, written
    once the command was dispatched: what dispatching it imported is above the line)."""
    return [i for i, line in enumerate(lines) if re.search(rf"\b{action} -> ", line)]


def test_with_goal_servers_the_stop_path_is_loaded_before_ready(tmp_path: Path,
                                                                domain_id: int) -> None:
    """The default config names both goal servers: their clients' cancel side is imported
    while the bridge starts, and a stop imports nothing of ours, before a goal or after one;
    the goal-sending side is loaded by the first goal (a move, not a stop: issue 27), and
    the server side of actions and services is never loaded."""
    with sim_robot(domain_id):
        proc = config_run(tmp_path, domain_id)
        try:
            first_stop = post(proc.url, TOKEN, {"action": "stop"})
            sent = post(proc.url, TOKEN, {"action": "navigate",
                                          "params": {"x": 1.0, "y": 0.0, "yaw": 0.0}})
            stopped = post(proc.url, TOKEN, {"action": "stop"})
            proc.signal(signal.SIGINT)
            assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
        finally:
            proc.kill()
    assert first_stop[0] == 200 and stopped[0] == 200, (first_stop, stopped)
    assert sent[0] == 200 and sent[1].get("goal_id"), sent  # accepted: the server is there
    started, serving = start_and_serving(proc)
    assert not GOAL_CLIENT - started, f"not imported at start: {sorted(GOAL_CLIENT - started)}"
    assert not GOAL_SENDING & started, f"imported at start: {sorted(GOAL_SENDING & started)}"
    lines = list(proc.stderr)
    running = next(i for i, line in enumerate(lines) if "bridge running" in line)
    (stop_1, stop_2), (goal,) = outcome_lines(lines, "stop"), outcome_lines(lines, "navigate")
    assert stop_1 < goal < stop_2, lines[stop_1:]
    before_goal, with_goal = imported(lines[running:stop_1]), imported(lines[stop_1:goal])
    assert not ours(before_goal), f"a stop before any goal imported {sorted(ours(before_goal))}"
    assert not GOAL_SENDING - with_goal, \
        f"the first goal did not load {sorted(GOAL_SENDING - with_goal)}"
    # Up to the stop's own outcome: the leaving's closing checkpoint then writes a start
    # point, which imports the log's replay again (governance.resume.write_point).
    after_goal = imported(lines[goal:stop_2 + 1])
    assert not ours(after_goal), f"after the goal, a stop imported {sorted(ours(after_goal))}"
    # Where the server side lives, and that the run never loaded it.
    assert {c.__module__ for c in (ActionServer, ServerGoal, ServiceServer)} <= SERVER_SIDE
    served = SERVER_SIDE & (started | serving)
    assert not served, f"a bridge imported {sorted(served)}"


def ours(modules: set[str]) -> set[str]:
    return {m for m in modules if m.startswith("rcan_rtps")}


# Only a start runs them (issue 27, item 6): the audit log's replay (`Governor.from_config`),
# the IDL parser and the XTypes describer (the start loads and describes every type a stop
# needs), let go of by the start once the robot side is built (`rcan_rtps._modules`).
START_ONLY = {"rcan_rtps.governance.resume", "rcan_rtps.ros.typesys.idl_parser",
              "rcan_rtps.ros.typesys.xtypes"}
# Only an arm that can move needs them: loaded at start when the config names arms, else by
# the first arm command, never by a stop (issue 27, item 6).
ARM_HOLDS = {"rcan_rtps.bridge.arm_holds", "rcan_rtps.bridge.desired_path"}

# A bridge started in-process as `run` starts it, then let go of what `run` lets go of before
# its ready line: which of our modules are still imported, and which start-only code is still
# alive (a reference kept to it anywhere would keep its module's memory). The start-only
# modules are imported first, so that the weak references are to what the start uses.
STARTED_AND_RELEASED = """
import asyncio, importlib, json, sys, weakref
from rcan_rtps.bridge.runtime import Bridge, BridgeOptions
from rcan_rtps.cli.run_cmd import release_free_memory
from rcan_rtps.config import load_config

code = [weakref.ref(vars(importlib.import_module(module))[name]) for module, name in
        (("rcan_rtps.governance.resume", "resume"),
         ("rcan_rtps.ros.typesys.idl_parser", "parse_idl"),
         ("rcan_rtps.ros.typesys.xtypes", "describe"))]

async def main():
    env = {"RCAN_BRIDGE_TOKEN": sys.argv[2]}
    bridge = Bridge(load_config(sys.argv[1], env=env),
                    BridgeOptions(port=0, host="127.0.0.1", mdns=False, env=env))
    bridge.prepare()
    await bridge.start()
    try:
        release_free_memory()
        print(json.dumps({"modules": sorted(m for m in sys.modules if m.startswith("rcan_rtps")),
                          "alive": [ref().__name__ for ref in code if ref() is not None]}))
    finally:
        await bridge.stop()

asyncio.run(main())
"""


def idle_config(tmp_path: Path, domain_id: int, ros2_extra: str = "") -> Path:
    state = tmp_path / "state"
    state.mkdir(mode=0o700)
    config = tmp_path / "robot.rcan.yaml"
    config.write_text(
        "robot: {ruri: rcan://registry.local/acme/rover/unit-0001}\n"
        "bridge:\n"
        f"  ros2: {{namespace: /robot1, domain_id: {domain_id}{ros2_extra}}}\n"
        "  api: {auth_token_env: RCAN_BRIDGE_TOKEN}\n"
        "  safety: {max_linear_vel: 1.0, max_angular_vel: 1.0, session_timeout_s: 3600}\n"
        f"  audit: {{path: {state / 'audit.jsonl'}, key_path: {state / 'audit.key'}}}\n")
    return config


def started_and_released(config: Path, domain_id: int) -> dict[str, object]:
    done = subprocess.run([sys.executable, "-c", STARTED_AND_RELEASED, str(config), TOKEN],
                          capture_output=True, text=True, timeout=120, env=child_env(domain_id))
    assert done.returncode == 0, done.stderr
    found: dict[str, object] = json.loads(done.stdout.splitlines()[-1])
    return found


TARGET = 1.5  # rad, 20 s away: the sim's elbow is far from it when stopped


def elbow(url: str) -> tuple[float, float] | None:
    """The sim's elbow as the bridge last heard it: (position, velocity)."""
    joints = json.loads(get(url + "/api/status", TOKEN)[1])["telemetry"]["joints"] or {}
    names, positions, velocities = (joints.get(k) or [] for k in
                                    ("names", "positions", "velocities"))
    if "elbow" not in names or len(velocities) != len(names):
        return None
    i = names.index("elbow")
    return float(positions[i]), float(velocities[i])


def elbow_when(url: str, wanted: Callable[[float, float], bool],
               timeout: float = 10.0) -> tuple[float, float] | None:
    """The elbow once `wanted(position, velocity)` (None if not within `timeout`)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = elbow(url)
        if found is not None and wanted(*found):
            return found
        time.sleep(0.1)  # the sim publishes joint_states at 10 Hz
    return None


ARMS = ", arms: {left: {topic: left_arm/joint_trajectory, joints: [l_shoulder]}}"


def test_an_idle_bridge_holds_no_start_only_or_arm_code(tmp_path: Path, domain_id: int) -> None:
    """Started, then released as `run` does before its ready line: the start-only modules are
    gone and nothing keeps their code alive; with no arm configured, the arms' holds are not
    loaded."""
    found = started_and_released(idle_config(tmp_path, domain_id), domain_id)
    modules = set(found["modules"])  # type: ignore[call-overload]
    assert "rcan_rtps.bridge.runtime" in modules  # the list is the run's
    assert not START_ONLY & modules, f"still imported: {sorted(START_ONLY & modules)}"
    assert found["alive"] == [], f"something keeps {found['alive']} alive"
    assert not ARM_HOLDS & modules, f"imported with no arm: {sorted(ARM_HOLDS & modules)}"


def test_a_bridge_with_arms_loads_their_holds_at_start(tmp_path: Path, domain_id: int) -> None:
    found = started_and_released(idle_config(tmp_path, domain_id, ARMS), domain_id)
    modules = set(found["modules"])  # type: ignore[call-overload]
    assert not ARM_HOLDS - modules, f"not loaded at start: {sorted(ARM_HOLDS - modules)}"


def test_the_first_arm_command_loads_the_holds_and_a_stop_holds_its_arm(
        tmp_path: Path, domain_id: int) -> None:
    """No arm configured (the default trajectory topic): a stop before any arm command
    imports nothing of ours; the first arm_joint loads the holds before its outcome is
    written and is executed; the stop right after it holds the arm (its entry says so) and
    imports nothing."""
    with sim_robot(domain_id):
        proc = config_run(tmp_path, domain_id)
        try:
            first_stop = post(proc.url, TOKEN, {"action": "stop"})
            moved = post(proc.url, TOKEN, {"action": "arm_joint", "params": {
                "joints": ["elbow"], "positions": [TARGET], "duration_s": 20.0}})
            moving = elbow_when(proc.url, lambda _, velocity: velocity > 0.0)
            stopped = post(proc.url, TOKEN, {"action": "stop"})
            held = elbow_when(proc.url, lambda _, velocity: velocity == 0.0)
            proc.signal(signal.SIGINT)
            assert proc.wait(EXIT_TIMEOUT) == 0, proc.output()
        finally:
            proc.kill()
    assert first_stop[0] == 200 and stopped[0] == 200, (first_stop, stopped, proc.output())
    assert moved[0] == 200 and moved[1].get("outcome") == "executed", moved
    started, _ = start_and_serving(proc)
    assert not ARM_HOLDS & started, f"imported at start: {sorted(ARM_HOLDS & started)}"
    lines = list(proc.stderr)
    running = next(i for i, line in enumerate(lines) if "bridge running" in line)
    (stop_1, stop_2), (arm,) = outcome_lines(lines, "stop"), outcome_lines(lines, "arm_joint")
    assert stop_1 < arm < stop_2, lines[stop_1:]
    before_arm, with_arm = imported(lines[running:stop_1]), imported(lines[stop_1:arm])
    assert not ours(before_arm), f"a stop before any arm imported {sorted(ours(before_arm))}"
    assert not ARM_HOLDS - with_arm, f"the arm command did not load {sorted(ARM_HOLDS - with_arm)}"
    after_arm = imported(lines[arm:stop_2 + 1])  # (as after_goal above)
    assert not ours(after_arm), f"after the arm command, a stop imported {sorted(ours(after_arm))}"
    # Held where it was: moving, then at rest far from the target it was 20 s from.
    assert moving is not None and held is not None and held[0] < TARGET / 2, (moving, held)
