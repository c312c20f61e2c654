"""`rcan-rtps sim`: the simulated robot as its own ROS 2 node (no ROS install needed)."""

from __future__ import annotations

import argparse
import asyncio
import contextlib

from .. import _stop_signals as stop_signals
from ..ros.participant import RosNode
from ..sim.docking import DockingServer
from ..sim.navigation import NavigationServer
from ..sim.others import warn_of_other_robots
from ..sim.parameters import serve_parameters
from ..sim.robot import SimParams, SimRobot
from ._common import make_store


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("sim", help="run a simulated differential-drive robot")
    parser.add_argument("--namespace", default="/robot1",
                        help="ROS namespace of the robot's node and topics (default /robot1)")
    parser.add_argument("--node-name", default="sim_robot", help="node name (default sim_robot)")
    parser.add_argument("--cmd-vel-type", default="geometry_msgs/msg/Twist",
                        choices=("geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped"),
                        help="type the robot takes on cmd_vel (default Twist)")
    parser.add_argument("--rate", type=float, default=50.0, help="odometry rate (Hz)")
    parser.add_argument("--cmd-timeout", type=float, default=0.5,
                        help="stop when no cmd_vel arrived for this long (s)")
    parser.add_argument("--nav-action", default="navigate_to_pose",
                        help="its nav2 NavigateToPose server (default navigate_to_pose)")
    parser.add_argument("--dock-action", default="dock_robot",
                        help="its nav2 DockRobot server, dock id `home` (default dock_robot)")
    parser.set_defaults(func=lambda a: stop_signals.run(_run(a)))


async def _run(args: argparse.Namespace) -> int:
    stop = asyncio.Event()
    # Ctrl-C, SIGTERM or SIGHUP: the robot's loop ends, its servers close, its node leaves
    # the graph; a stop it was made for, so exit 0 (as `run`).
    with stop_signals.taking_over(lambda sig: stop.set()), \
            RosNode(args.node_name, args.namespace, domain_id=args.domain_id,
                    localhost=args.localhost, store=make_store(args)) as node:
        robot = SimRobot(node, cmd_vel_type=args.cmd_vel_type,
                         params=SimParams(rate_hz=args.rate, cmd_timeout_s=args.cmd_timeout))
        nav = NavigationServer(robot, args.nav_action)
        docking = DockingServer(robot, args.dock_action)
        parameters = serve_parameters(robot)
        print(f"rcan-rtps sim ready node={node.fqn} domain={node.domain_id}", flush=True)
        looking = asyncio.create_task(warn_of_other_robots(node))  # beside the robot's loop
        try:
            await robot.run(stop)
        finally:
            looking.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await looking
            await nav.close()
            await docking.close()
            await parameters.close()
    return 0
