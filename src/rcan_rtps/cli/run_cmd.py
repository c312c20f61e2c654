"""`rcan-rtps run`: the governed bridge (and, with `--sim`, the simulated robot beside it)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import gc
import logging
import os
import sys
import threading
from collections.abc import Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .._modules import let_go
from ..bridge.demo import (
    OWNER_TOKEN_ENV,
    USER_TOKEN_ENV,
    VIEWER_TOKEN_ENV,
    default_state_dir,
    demo_config,
    demo_tokens,
)
from ..bridge.watchdog import DEFAULT_STALL_S, LoopWatchdog, SignalStopper
from ..config import RcanConfig, load_config

if TYPE_CHECKING:
    from ..bridge.runtime import Bridge

LOOP_ENV = "RCAN_RTPS_LOOP"  # "asyncio": the standard event loop even when uvloop is installed


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "run", help="run the governed bridge", epilog=TOKENS_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, metavar="FILE",
                        help=".rcan.yaml (default with --sim: built in)")
    parser.add_argument("--sim", action="store_true",
                        help="also run the simulated robot; loopback-only unless --lan")
    parser.add_argument("--lan", action="store_true", help="with --sim: discover beyond loopback")
    parser.add_argument("--host", help="override api.host")
    parser.add_argument("--port", type=int, help="override api.port (0: any free port)")
    parser.add_argument("--state-dir", type=Path, help="--sim: audit log and key (default: "
                        "$XDG_STATE_HOME/rcan-rtps/sim)")
    parser.add_argument("--no-mdns", action="store_true", help="do not advertise over mDNS")
    parser.add_argument("--stall-report", type=float, default=DEFAULT_STALL_S, metavar="S",
                        help="log every thread's stack when the event loop stalls this long "
                        f"(default {DEFAULT_STALL_S:g} s; 0: off)")
    parser.set_defaults(func=_main)


TOKENS_EPILOG = f"""\
tokens: each principal's bearer token is read from the environment variable its
`token_env` names (bridge.api.principals; or bridge.api.auth_token_env), at least 16
bytes; `rcan-rtps config check FILE` lists those that are missing.
With --sim (the built-in config) the demo's tokens are made up per run and printed,
unless these variables hold them:
  {VIEWER_TOKEN_ENV:<24} GUEST `viewer`: reads status; may raise an e-stop
  {USER_TOKEN_ENV:<24} USER `operator`: may command motion
  {OWNER_TOKEN_ENV:<24} OWNER `owner`: also approves held commands, clears e-stops
"""
STALL_HOOK_ENV = "RCAN_RTPS_TEST_STALL_S"  # tests only: block the loop this long once ready
SLOW_START_HOOK_ENV = "RCAN_RTPS_TEST_SLOW_START_S"  # tests only: a start this much slower


def _main(args: argparse.Namespace) -> int:
    # First, before any thread exists: SIGINT/SIGTERM/SIGHUP always end the process, even with the
    # event loop stuck (graceful stop, bounded; a second SIGINT or SIGTERM exits at once).
    stopper = SignalStopper()
    try:
        return run_loop(_run(args, stopper))
    finally:
        stopper.finished()


def run_loop(main: Coroutine[Any, Any, int]) -> int:
    """`main` on uvloop when it is installed (the `fast` extra): its loop turns cost a fraction
    of asyncio's, which is most of a governed command's CPU. Else, or with RCAN_RTPS_LOOP=
    asyncio, on the standard loop."""
    uvloop = _uvloop()
    logging.getLogger(__name__).debug(
        "event loop: %s", "asyncio" if uvloop is None else f"uvloop {uvloop.__version__}")
    if uvloop is None:
        return asyncio.run(main)
    # A uvloop loop for this run only, on every Python: 3.10's asyncio.run takes no loop
    # factory, and uvloop's policy, set instead, made every later loop of the process (and
    # other threads' loops meanwhile) a uvloop one, RCAN_RTPS_LOOP=asyncio or not.
    result: int = uvloop.run(main)
    return result


def _uvloop() -> Any:
    if os.environ.get(LOOP_ENV, "").lower() == "asyncio":
        return None
    try:
        import uvloop
    except ImportError:
        return None
    return uvloop


def _config(args: argparse.Namespace, env: dict[str, str]) -> RcanConfig:
    if args.config is not None:
        return load_config(args.config, env=env)
    if not args.sim:
        raise ValueError("--config FILE is required (or --sim for the built-in demo)")
    from ..ros.participant import resolve_domain_id  # cyclonedds: after the config (_read_config)
    return demo_config(state_dir=args.state_dir or default_state_dir(),
                       port=args.port or 8765,  # 0 (any free port) is the server's to pick
                       domain_id=resolve_domain_id(args.domain_id, env),
                       namespace="/robot1", env=env)


# PyYAML and the modules that read a config: a run reads one, once.
_LOADER = ("yaml", "rcan_rtps.config._load", "rcan_rtps.config._schema")


def _read_config(args: argparse.Namespace, env: dict[str, str]) -> RcanConfig:
    """The config, read before the bridge's libraries are imported; then the loader is let go
    of, and their imports reuse its memory (~0.9 MB of idle RSS). PyYAML is imported without
    libyaml's binding for that (which would keep it alive for good); the loader is pure
    Python anyway (yaml.SafeLoader)."""
    if "yaml" in sys.modules:  # already imported (in-process tests): nothing to let go of
        return _config(args, env)
    sys.modules["yaml._yaml"] = None  # type: ignore[assignment]  # an ImportError for PyYAML
    try:
        return _config(args, env)
    finally:
        del sys.modules["yaml._yaml"]
        let_go([n for n in sys.modules if n.split(".")[0] == "yaml" or n in _LOADER])
        gc.collect()  # the modules' reference cycles


CURL_EXAMPLES = (
    "curl -s -H 'Authorization: Bearer {token}' {url}/api/status",
    "curl -s -H 'Authorization: Bearer {token}' -H 'Content-Type: application/json' "
    "-d '{{\"action\": \"move\", \"params\": {{\"linear_x\": 0.5}}}}' {url}/api/command",
    "curl -s -H 'Authorization: Bearer {token}' -H 'Content-Type: application/json' "
    "-d '{{\"action\": \"navigate\", \"params\": {{\"x\": 2.0, \"y\": 1.0, \"yaw\": 0.0}}}}' "
    "{url}/api/command",
)


def _print_demo(url: str, env: dict[str, str], config: RcanConfig) -> None:
    user, owner, viewer = env[USER_TOKEN_ENV], env[OWNER_TOKEN_ENV], env[VIEWER_TOKEN_ENV]
    print(f"demo tokens: USER (operator) {user}\n             OWNER (owner)   {owner}\n"
          f"             GUEST (viewer)  {viewer}\n"
          "(a client that sends motion commands heartbeats: POST /api/heartbeat at least "
          f"every {config.bridge.safety.session_timeout_s:g} s, else the robot is halted)")
    print(f"audit log: {config.bridge.audit.path}")
    print("try:")
    for example in CURL_EXAMPLES:
        print("  " + example.format(token=user, url=url))
    print(flush=True)


async def _run(args: argparse.Namespace, stopper: SignalStopper) -> int:
    env = dict(os.environ)
    if args.sim:
        env.update(demo_tokens(env))
    config = _read_config(args, env)
    from ..bridge.runtime import Bridge, BridgeOptions  # after the config: see _read_config
    localhost = args.localhost if args.localhost is not None else (
        True if args.sim and not args.lan else None)
    # The demo keeps mDNS on loopback too: it must not talk to the LAN unless asked.
    mdns_interfaces = ["127.0.0.1"] if args.sim and not args.lan else None
    bridge = Bridge(config, BridgeOptions(localhost=localhost, host=args.host, port=args.port,
                                          mdns=not args.no_mdns, mdns_interfaces=mdns_interfaces,
                                          env=env))
    bridge.prepare()  # tokens, TLS, key, port: fail before anything joins the domain
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    stopper.attach(loop, stop.set)
    # Each part's cleanup is registered once it exists: any failure below unwinds exactly
    # what was started, the bridge first (it halts the robot), the watchdog last.
    async with contextlib.AsyncExitStack() as parts:
        parts.push_async_callback(bridge.stop)  # releases the port should the sim fail
        if args.stall_report > 0:
            watchdog = LoopWatchdog(loop, args.stall_report)
            watchdog.start()
            parts.callback(watchdog.stop)
        if args.sim:
            _start_sim(parts, config, localhost, stop)
        parts.push_async_callback(bridge.stop)  # again (idempotent): before the sim stops
        url = await _start_unless_stopped(bridge, stop, env)
        if url is None:
            return 0  # Ctrl-C (or SIGTERM, SIGHUP) during start: no banner, no tokens
        release_free_memory()
        # What start-up built lives as long as the process: out of the collector's sight, so a
        # collection during a command scans only what commands allocate (ms → µs pauses).
        gc.freeze()
        print(f"rcan-rtps ready api={url}", flush=True)
        if args.sim:
            _print_demo(url, env, config)
        _test_stall(loop, env)
        await stop.wait()
    return 0


def release_free_memory() -> None:
    """Start-up's garbage collected and the C heap's free pages handed back to the system
    (glibc's malloc_trim; elsewhere nothing more): ~0.6 MB of idle RSS. The start-only
    modules were let go of by the start itself (`Bridge._acquire`)."""
    gc.collect()
    if not sys.platform.startswith("linux"):
        return
    try:
        trim = ctypes.CDLL(None).malloc_trim  # ctypes: already imported by cyclonedds
    except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
        return
    trim(0)


async def _start_unless_stopped(bridge: Bridge, stop: asyncio.Event,
                                env: dict[str, str]) -> str | None:
    """The bridge's URL once started, or None if a stop was asked for first (the start is
    then cancelled, which releases what it had acquired)."""
    async def start() -> str:
        late = float(env.get(SLOW_START_HOOK_ENV, "0") or 0)
        if late > 0:
            logging.getLogger(__name__).warning("test hook: starting %g s late", late)
            await asyncio.sleep(late)
        return await bridge.start()

    starting = asyncio.ensure_future(start())
    stopping = asyncio.ensure_future(stop.wait())
    await asyncio.wait({starting, stopping}, return_when=asyncio.FIRST_COMPLETED)
    stopping.cancel()
    if stop.is_set():
        starting.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await starting
        return None
    return starting.result()


def _start_sim(parts: contextlib.AsyncExitStack, config: RcanConfig, localhost: bool | None,
               stop: asyncio.Event) -> None:
    """The simulated robot and its navigation and docking servers, on a node of their own."""
    from ..ros.participant import RosNode  # --sim only: a bridge run leaves these unimported
    from ..sim.camera import SimCamera
    from ..sim.docking import DockingServer
    from ..sim.navigation import NavigationServer
    from ..sim.others import warn_of_other_robots
    from ..sim.parameters import serve_parameters
    from ..sim.robot import SimRobot

    ros2 = config.bridge.ros2
    # (the domain's first node: it sets what the bridge's shares, the bound on sample size)
    sim_node = RosNode("sim_robot", ros2.namespace or "/", domain_id=ros2.domain_id,
                       distro=ros2.distro, localhost=localhost,
                       max_sample_bytes=ros2.max_sample_bytes)
    parts.callback(sim_node.close)
    robot = SimRobot(sim_node, cmd_vel_type=ros2.cmd_vel_type)
    # A goal server the config names none of (null) is not simulated either.
    servers: list[NavigationServer | DockingServer] = []
    if ros2.nav_action is not None:
        servers.append(NavigationServer(robot, ros2.nav_action))
    if ros2.dock_action is not None:
        servers.append(DockingServer(robot, ros2.dock_action))
    parameters = serve_parameters(robot)
    sim_task = asyncio.create_task(robot.run(stop))
    camera_task = asyncio.create_task(SimCamera(sim_node, robot).run(stop))
    # A second robot on these topics is warned of, once; the look is no part of the robot.
    looking = asyncio.create_task(warn_of_other_robots(sim_node))

    async def stop_sim() -> None:
        stop.set()
        looking.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await looking
        for server in servers:
            await server.close()
        await parameters.close()
        await sim_task
        await camera_task

    parts.push_async_callback(stop_sim)


def _test_stall(loop: asyncio.AbstractEventLoop, env: dict[str, str]) -> None:
    """A test hook: RCAN_RTPS_TEST_STALL_S=S blocks the event loop for S s, in C (a lock
    wait), half a second after the ready line."""
    seconds = float(env.get(STALL_HOOK_ENV, "0") or 0)
    if seconds > 0:
        def stall() -> None:
            logging.getLogger(__name__).warning("test hook: blocking the loop for %g s",
                                                seconds)
            threading.Event().wait(seconds)

        loop.call_later(0.5, stall)
