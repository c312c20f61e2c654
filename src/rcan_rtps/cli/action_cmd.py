"""`rcan-rtps action list|info|send_goal`, shaped like `ros2 action`."""

from __future__ import annotations

import argparse
import asyncio
import sys
import uuid
from typing import Any

from .. import _stop_signals as stop_signals
from ..ros.action_goals import ClientGoal
from ..ros.actions import ActionClient, GoalState
from ..ros.graph import Direction, RosGraph, node_fqn, shared_graph
from ..ros.names import EndpointKind, action_names
from ..ros.services import RequestMapping
from ._common import VALUES_HELP, dump, make_node, parse_values, warn_if_alone
from ._governed import UNGOVERNED, GovernorGuard, action_topics
from ._options import add_spin_time
from .service_cmd import MAPPING_HELP, MAPPINGS


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser("action", help="inspect actions and send goals")
    actions = parser.add_subparsers(dest="action_command", required=True)

    listing = actions.add_parser("list", help="actions on the graph")
    listing.add_argument("-t", "--show-types", action="store_true",
                         help="show each action's type")
    add_spin_time(listing)
    listing.set_defaults(func=lambda a: stop_signals.run(_list(a)))

    info = actions.add_parser("info", help="servers and clients of an action")
    info.add_argument("action", metavar="NAME", help="action name, e.g. /robot1/navigate_to_pose")
    info.add_argument("-t", "--show-types", action="store_true",
                      help="show the action type of each server and client")
    add_spin_time(info)
    info.set_defaults(func=lambda a: stop_signals.run(_info(a)))

    send = actions.add_parser("send_goal", help="send a goal and wait for its result "
                                                "(Ctrl-C, SIGTERM or SIGHUP cancels the goal)")
    send.add_argument("action", metavar="NAME", help="action name, e.g. /robot1/navigate_to_pose")
    send.add_argument("type", metavar="TYPE",
                      help="action type, e.g. nav2_msgs/action/NavigateToPose")
    send.add_argument("values", metavar="VALUES", nargs="?", default="{}", help=VALUES_HELP)
    send.add_argument("-f", "--feedback", action="store_true", help="print feedback")
    send.add_argument("--timeout", type=float, default=10.0,
                      help="seconds to find the server and have the goal answered")
    send.add_argument("--mapping", choices=MAPPINGS, default="auto", help=MAPPING_HELP)
    send.add_argument(UNGOVERNED[0], action="store_true", help=UNGOVERNED[1])
    send.set_defaults(func=lambda a: stop_signals.run(_send_goal(a)))


async def _list(args: argparse.Namespace) -> int:
    with make_node(args) as node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        for name, types in graph.actions().items():
            print(f"{name} [{', '.join(types)}]" if args.show_types else name)
        warn_if_alone(args, node, graph)
    return 0


async def _info(args: argparse.Namespace) -> int:
    with make_node(args) as node:
        graph = RosGraph(node)
        await graph.settle(args.spin_time)
        name = node.resolve(args.action)
        send_goal = action_names(name)["send_goal"]
        ends = [e for e in graph.endpoints()
                if e.ros_name == send_goal and e.kind is EndpointKind.REQUEST]
        if not ends:
            print(f"Action not found: {name}", file=sys.stderr)
            return 1
        print(f"Action: {name}")
        for title, direction in (("clients", Direction.PUBLISHER),
                                 ("servers", Direction.SUBSCRIPTION)):
            found = sorted({(node_fqn(e.node_namespace, e.node_name),
                             e.ros_type.removesuffix("_SendGoal"))
                            for e in ends if e.direction is direction})
            print(f"Action {title}: {len(found)}")
            for fqn, type_name in found:
                print(f"    {fqn} [{type_name}]" if args.show_types else f"    {fqn}")
    return 0


async def _send_goal(args: argparse.Namespace) -> int:
    values = parse_values(args.values)
    with make_node(args) as node:
        client = ActionClient(node, args.action, args.type, mapping=RequestMapping(args.mapping))
        goal_type = client.types.goal.name
        message = node.values.build(goal_type, values)  # bad values fail before the graph
        print("Waiting for an action server to become available...", flush=True)
        await client.wait_for_server(args.timeout)  # a stop until here ends it: nothing sent
        await GovernorGuard(shared_graph(node), action_topics(client.name),
                            allowed=args.ungoverned).look_before_sending()
        print("Sending goal:\n" + _indent(dump(node.values.to_plain(goal_type, message))),
              flush=True)
        # From here a goal may be running on the server: Ctrl-C, SIGTERM or SIGHUP (its
        # terminal closed) must not leave the robot driving to a goal nobody follows. Each
        # cancels it on the server before the command ends (exit 128 + the signal).
        interrupted = asyncio.Event()
        with stop_signals.taking_over(lambda sig: interrupted.set()) as stopping:
            code = await _goal(args, client, message, interrupted)
            return code if stopping.received is None else 128 + stopping.received


async def _goal(args: argparse.Namespace, client: ActionClient, message: Any,
                interrupted: asyncio.Event) -> int:
    """Sends the goal and follows it to its end, or cancels it once `interrupted`."""
    goal = await client.send_goal(message, args.timeout)
    if not goal.accepted:
        print("Goal was rejected.", flush=True)
        return 1
    print(f"Goal accepted with ID: {uuid.UUID(bytes=goal.goal_id).hex}\n", flush=True)
    follow = asyncio.ensure_future(_follow(client, goal, args.feedback))
    stop = asyncio.ensure_future(interrupted.wait())
    await asyncio.wait({follow, stop}, return_when=asyncio.FIRST_COMPLETED)
    stop.cancel()
    if follow.done():
        return follow.result()
    follow.cancel()
    print("Canceling goal...", flush=True)
    canceling = await goal.cancel(args.timeout)
    print("Goal canceled." if canceling else "Cancel request refused.", flush=True)
    outcome = await goal.result(args.timeout)
    print(f"Goal finished with status: {outcome.state.name}", flush=True)
    return 1


async def _follow(client: ActionClient, goal: ClientGoal, feedback: bool) -> int:
    """Prints the feedback (with `feedback`) and the result, as soon as it is in: after the
    feedback that came before the goal's end, before what a dropped datagram's repair brings
    after it (`feedback()` waits for that, up to REPAIR_S); the status line comes last."""
    printing = asyncio.ensure_future(_print_feedback(client, goal)) if feedback else None
    try:
        if printing is not None:
            settled = asyncio.ensure_future(goal.end_settled.wait())
            await asyncio.wait({printing, settled}, return_when=asyncio.FIRST_COMPLETED)
            settled.cancel()
        outcome = await goal.result(timeout=365 * 24 * 3600.0)  # a goal may run for long
        if outcome.result is not None:
            plain = client.node.values.to_plain(client.types.result.name, outcome.result)
            print("Result:\n" + _indent(dump(plain)) + "\n", flush=True)
        elif outcome.detail:
            print(outcome.detail, flush=True)
        if printing is not None:
            await printing
    finally:
        if printing is not None:
            printing.cancel()  # Ctrl-C: the goal is canceled, its feedback no longer printed
    print(f"Goal finished with status: {outcome.state.name}", flush=True)
    return 0 if outcome.state is GoalState.SUCCEEDED else 1


async def _print_feedback(client: ActionClient, goal: ClientGoal) -> None:
    feedback_type = client.types.feedback.name
    async for message in goal.feedback():
        plain = client.node.values.to_plain(feedback_type, message)
        print("Feedback:\n" + _indent(dump(plain)) + "\n", flush=True)


def _indent(text: str) -> str:
    return "\n".join("  " + line for line in text.splitlines())
