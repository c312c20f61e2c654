"""A real rclpy node driven over JSON lines on stdin/stdout — the test oracle.

Runs with the ROS 2 environment's interpreter (never the product's). Each request is
`{"id": N, "op": NAME, ...}`; each answer `{"id": N, "ok": true, "result": ...}` or
`{"id": N, "ok": false, "error": "..."}`. rclpy spins in a background thread;
received messages are kept per topic until taken.
"""

from __future__ import annotations

import array
import importlib
import json
import os
import sys
import threading
import time
import traceback
from typing import Any

import rclpy
from rclpy.action import ActionClient, ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.serialization import deserialize_message, serialize_message
from rosidl_parser.definition import AbstractNestedType, NamespacedType


def load_type(name: str) -> Any:
    pkg, kind, short = name.split("/")
    module = importlib.import_module(f"{pkg}.{kind}")
    for suffix, attr in (("_Request", "Request"), ("_Response", "Response")):
        if kind == "srv" and short.endswith(suffix):
            return getattr(getattr(module, short[: -len(suffix)]), attr)
    if kind == "action":
        for part in ("Goal", "Result", "Feedback"):
            if short.endswith("_" + part):
                return getattr(getattr(module, short[: -len(part) - 1]), part)
        impl_parts = {
            "_SendGoal_Request": ("SendGoalService", "Request"),
            "_SendGoal_Response": ("SendGoalService", "Response"),
            "_GetResult_Request": ("GetResultService", "Request"),
            "_GetResult_Response": ("GetResultService", "Response"),
            "_FeedbackMessage": ("FeedbackMessage", None),
        }
        for suffix, (impl, attr) in impl_parts.items():
            if short.endswith(suffix):
                base = getattr(getattr(module, short[: -len(suffix)]).Impl, impl)
                return getattr(base, attr) if attr else base
    return getattr(module, short)


def _nested_class(slot: NamespacedType) -> Any:
    return load_type("/".join([*slot.namespaces, slot.name]))


def fill(msg: Any, data: dict[str, Any]) -> Any:
    for attr, slot in zip(msg.__slots__, msg.SLOT_TYPES, strict=False):
        name = attr.lstrip("_")
        if name not in data:
            continue
        value = data[name]
        if isinstance(slot, NamespacedType):
            value = fill(_nested_class(slot)(), value) if isinstance(value, dict) else value
        elif isinstance(slot, AbstractNestedType):
            inner = slot.value_type
            if isinstance(inner, NamespacedType):
                cls = _nested_class(inner)
                value = [fill(cls(), v) for v in value]
            elif getattr(inner, "typename", "") == "octet":
                value = [bytes([v]) for v in value]
        elif getattr(slot, "typename", "") == "octet":
            value = bytes([value])
        setattr(msg, name, value)
    return msg


def plain(value: Any) -> Any:
    if hasattr(value, "get_fields_and_field_types"):
        return {name: plain(getattr(value, name)) for name in value.get_fields_and_field_types()}
    if isinstance(value, bytes) and len(value) == 1:
        return value[0]  # a single `byte` field, or one element of a byte array
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (list, tuple, array.array)) or type(value).__name__ == "ndarray":
        return [plain(v) for v in value]
    if hasattr(value, "item"):  # numpy scalar
        return value.item()
    return value


def make_qos(name: str) -> QoSProfile:
    if name == "sensor":
        return qos_profile_sensor_data
    if name.startswith("transient_local"):  # `transient_local:N`: keep-last N (default 1)
        _, _, depth = name.partition(":")
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=int(depth or 1),
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    if name == "deep":  # reliable, a history no burst overwrites: loss shows as loss
        return QoSProfile(depth=100_000)
    return QoSProfile(depth=10)


class Agent:
    def __init__(self, node_name: str, namespace: str) -> None:
        rclpy.init()
        self.node = Node(node_name, namespace=namespace)
        # Benchmarks want SingleThreadedExecutor: rclpy's MultiThreadedExecutor delivers
        # bursts late, which would be measured as transport latency.
        single = os.environ.get("RCAN_ORACLE_EXECUTOR") == "single"
        self.executor = SingleThreadedExecutor() if single else MultiThreadedExecutor()
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self.received: dict[str, list[Any]] = {}
        self.matched: dict[str, int] = {}
        self.subscribers_matched: dict[str, int] = {}  # our publishers' matched readers
        self.publishers: dict[str, Any] = {}
        self.periodic: dict[str, threading.Event] = {}
        self.published: dict[str, int] = {}
        self.subscriptions: dict[str, Any] = {}
        self.services: dict[str, Any] = {}
        self.service_requests: dict[str, list[Any]] = {}
        self.action_servers: dict[str, Any] = {}
        self.action_clients: dict[str, Any] = {}
        self.clients: dict[str, Any] = {}  # service clients kept between ops (`client`)
        self.goals: dict[str, dict[str, Any]] = {}
        self.group = ReentrantCallbackGroup()
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    # -- ops ----------------------------------------------------------------------
    def op_ping(self) -> str:
        return "pong"

    def op_rmw(self) -> str:
        """The RMW this node runs on (RMW_IMPLEMENTATION chooses it in the Cyclone prefix)."""
        return str(rclpy.get_rmw_implementation_identifier())

    def op_serialize(self, type: str, value: dict[str, Any]) -> str:
        return serialize_message(fill(load_type(type)(), value)).hex()

    def op_deserialize(self, type: str, hex: str) -> Any:
        return plain(deserialize_message(bytes.fromhex(hex), load_type(type)))

    def op_roundtrip(self, type: str, value: dict[str, Any]) -> Any:
        return plain(fill(load_type(type)(), value))

    def op_publisher(self, topic: str, type: str, qos: str = "default") -> bool:
        def on_matched(status: Any, topic: str = topic) -> None:
            with self.lock:
                self.subscribers_matched[topic] = status.current_count

        self.publishers[topic] = self.node.create_publisher(
            load_type(type), topic, make_qos(qos),
            event_callbacks=PublisherEventCallbacks(matched=on_matched))
        return True

    def op_wait_subscribers_matched(self, topic: str, count: int = 1,
                                    timeout: float = 15.0) -> int:
        """Subscriptions matched by our publisher on `topic` at the DDS level: only then does a
        one-shot, volatile message reach them (a reader that matched our writer may not yet
        be matched by it; `wait_subscribers` counts them on the graph)."""
        return self._wait_count(self.subscribers_matched, topic, count, timeout)

    def op_unpublish(self, topic: str) -> bool:
        """Destroys our publisher on `topic` (a clean leave: readers see the writer go)."""
        return bool(self.node.destroy_publisher(self.publishers.pop(topic)))

    def op_publish(self, topic: str, type: str, value: dict[str, Any], count: int = 1,
                   period: float = 0.05) -> int:
        pub = self.publishers[topic]
        msg = fill(load_type(type)(), value)
        for _ in range(count):
            pub.publish(msg)
            time.sleep(period)
        return count

    def op_publish_periodic(self, topic: str, type: str, value: dict[str, Any],
                            rate: float = 100.0, stamp: bool = False) -> bool:
        """Publishes `value` on `topic` at `rate` Hz from a background thread until
        `stop_periodic` (the publisher is made by `publisher` first); with `stamp`, each
        message's header.stamp is the node clock's now."""
        pub = self.publishers[topic]
        msg = fill(load_type(type)(), value)
        stop = threading.Event()

        def loop() -> None:
            period = 1.0 / rate
            next_at = time.monotonic()
            while not stop.is_set():
                if stamp:
                    msg.header.stamp = self.node.get_clock().now().to_msg()
                pub.publish(msg)
                self.published[topic] = self.published.get(topic, 0) + 1
                next_at += period
                stop.wait(max(0.0, next_at - time.monotonic()))

        self.periodic[topic] = stop
        threading.Thread(target=loop, daemon=True).start()
        return True

    def op_stop_periodic(self, topic: str) -> int:
        """Stops a `publish_periodic` loop; returns how many messages it published."""
        self.periodic.pop(topic).set()
        return self.published.get(topic, 0)

    def op_subscribe(self, topic: str, type: str, qos: str = "default",
                     arrival: bool = False) -> bool:
        """Keeps each message received on `topic`; with `arrival`, as `{"arrived_ns":
        CLOCK_MONOTONIC ns when it came, "msg": the message}`."""
        self.received.setdefault(topic, [])

        def on_message(msg: Any, topic: str = topic) -> None:
            got = plain(msg)
            if arrival:
                got = {"arrived_ns": time.monotonic_ns(), "msg": got}
            with self.lock:
                self.received[topic].append(got)

        def on_matched(status: Any, topic: str = topic) -> None:
            with self.lock:
                self.matched[topic] = status.current_count

        self.subscriptions[topic] = self.node.create_subscription(
            load_type(type), topic, on_message, make_qos(qos),
            event_callbacks=SubscriptionEventCallbacks(matched=on_matched))
        return True

    def op_wait_matched(self, topic: str, count: int = 1, timeout: float = 15.0) -> int:
        """Publishers matched by our subscription at the DDS level (not just on the graph):
        only then is a one-shot, volatile message sure to reach it."""
        return self._wait_count(self.matched, topic, count, timeout)

    def _wait_count(self, counts: dict[str, int], topic: str, count: int,
                    timeout: float) -> int:
        """`counts[topic]` (kept by match callbacks, under the lock) once it reaches `count`,
        or as it is at `timeout`."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                n = counts.get(topic, 0)
            if n >= count:
                return n
            time.sleep(0.02)
        with self.lock:
            return counts.get(topic, 0)

    def op_subscribe_timed(self, topic: str, type: str, field: str = "linear.x",
                           qos: str = "default", clock: str = "arrival") -> bool:
        """Records (CLOCK_MONOTONIC ns at arrival, value of `field`) per message: latency
        benchmarks compare it with the sender's monotonic clock (same host). `clock="source"`:
        the writer's source timestamp (ns since the epoch) instead, when it wrote the sample,
        whatever delayed its delivery here."""
        self.received.setdefault(topic, [])
        path = field.split(".")

        def on_message(msg: Any, info: Any, topic: str = topic) -> None:
            arrived = info["source_timestamp"] if clock == "source" else time.monotonic_ns()
            value = msg
            for part in path:
                value = getattr(value, part)
            with self.lock:
                self.received[topic].append([arrived, value])

        self.subscriptions[topic] = self.node.create_subscription(
            load_type(type), topic, on_message, make_qos(qos))
        return True

    def op_unsubscribe(self, topic: str) -> bool:
        """Destroys our subscription to `topic` (a clean leave: writers see the reader go)."""
        sub = self.subscriptions.pop(topic)
        return bool(self.node.destroy_subscription(sub))

    def op_take(self, topic: str) -> list[Any]:
        with self.lock:
            taken, self.received[topic] = self.received.get(topic, []), []
        return taken

    def op_wait_publishers(self, topic: str, count: int = 1, timeout: float = 10.0) -> int:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            n = self.node.count_publishers(topic)
            if n >= count:
                return n
            time.sleep(0.05)
        return self.node.count_publishers(topic)

    def op_wait_subscribers(self, topic: str, count: int = 1, timeout: float = 10.0) -> int:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            n = self.node.count_subscribers(topic)
            if n >= count:
                return n
            time.sleep(0.05)
        return self.node.count_subscribers(topic)

    def op_node_names(self) -> list[list[str]]:
        return [list(x) for x in self.node.get_node_names_and_namespaces()]

    def op_topic_names(self) -> list[list[Any]]:
        return [[n, list(t)] for n, t in self.node.get_topic_names_and_types()]

    def op_publishers_info(self, topic: str) -> list[dict[str, Any]]:
        return [_endpoint(i) for i in self.node.get_publishers_info_by_topic(topic)]

    def op_subscriptions_info(self, topic: str) -> list[dict[str, Any]]:
        return [_endpoint(i) for i in self.node.get_subscriptions_info_by_topic(topic)]

    def op_node_info(self, name: str, namespace: str) -> dict[str, list[list[Any]]]:
        """What rclpy's graph API reports for a node, per `ros2 node info` section."""
        from rclpy.action import (
            get_action_client_names_and_types_by_node,
            get_action_server_names_and_types_by_node,
        )

        node = self.node
        deadline = time.monotonic() + 10.0
        while (name, namespace) not in node.get_node_names_and_namespaces() \
                and time.monotonic() < deadline:
            time.sleep(0.05)
        found = {
            "Subscribers": node.get_subscriber_names_and_types_by_node(name, namespace),
            "Publishers": node.get_publisher_names_and_types_by_node(name, namespace),
            "Service Servers": node.get_service_names_and_types_by_node(name, namespace),
            "Service Clients": node.get_client_names_and_types_by_node(name, namespace),
            "Action Servers": get_action_server_names_and_types_by_node(node, name, namespace),
            "Action Clients": get_action_client_names_and_types_by_node(node, name, namespace),
        }
        return {k: [[n, list(t)] for n, t in v] for k, v in found.items()}

    def op_declare_parameter(self, name: str, value: Any) -> bool:
        self.node.declare_parameter(name, value)
        return True

    def op_get_parameter(self, name: str) -> Any:
        return plain(self.node.get_parameter(name).value)

    # -- services and actions (issue 3) ---------------------------------------------
    def op_service_server(self, name: str, type: str, delay: float = 0.0) -> bool:
        """Trigger answers `triggered #N`; SetBool echoes `data` into `success`."""
        self.service_requests[name] = []

        def handle(request: Any, response: Any, name: str = name) -> Any:
            with self.lock:
                self.service_requests[name].append(plain(request))
                count = len(self.service_requests[name])
            time.sleep(delay)
            if hasattr(request, "data"):
                response.success = request.data
                response.message = f"set to {request.data} (#{count})"
            else:
                response.success = True
                response.message = f"triggered #{count}"
            return response

        self.services[name] = self.node.create_service(
            load_type(type), name, handle, callback_group=self.group)
        return True

    def op_echo_server(self, name: str) -> bool:
        """test_msgs/srv/BasicTypes answering with a copy of each request (issue 12:
        a reply names its request, so a misattributed reply shows)."""
        from test_msgs.srv import BasicTypes

        self.service_requests[name] = []

        def handle(request: Any, response: Any, name: str = name) -> Any:
            with self.lock:
                self.service_requests[name].append(request.string_value)
            for field in request.get_fields_and_field_types():
                setattr(response, field, getattr(request, field))
            return response

        self.services[name] = self.node.create_service(
            BasicTypes, name, handle, callback_group=self.group)
        return True

    def op_service_requests(self, name: str) -> list[Any]:
        with self.lock:
            return list(self.service_requests.get(name, []))

    def op_service_call(self, name: str, type: str, value: dict[str, Any],
                        wait: float = 5.0) -> Any:
        """An rclpy client call; returns the response, {"no_service": true} or
        {"timeout": true} after `wait` seconds."""
        srv = load_type(type)
        client = self.node.create_client(srv, name, callback_group=self.group)
        try:
            if not client.wait_for_service(timeout_sec=wait):
                return {"no_service": True}
            future = client.call_async(fill(srv.Request(), value))
            deadline = time.monotonic() + wait
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.02)
            return plain(future.result()) if future.done() else {"timeout": True}
        finally:
            self.node.destroy_client(client)

    def op_client(self, key: str, name: str, type: str, wait: float = 10.0) -> bool:
        """An rclpy client of `name`, kept under `key` until `destroy_client` (a fresh
        request writer each time); whether it saw the server within `wait` seconds."""
        client = self.node.create_client(load_type(type), name, callback_group=self.group)
        self.clients[key] = client
        return bool(client.wait_for_service(timeout_sec=wait))

    def op_client_send(self, key: str, type: str, value: dict[str, Any]) -> bool:
        """Sends one request with the client under `key`, without waiting for its reply."""
        self.clients[key].call_async(fill(load_type(type).Request(), value))
        return True

    def op_destroy_client(self, key: str) -> bool:
        """Destroys the client under `key` (a clean leave: its writer and reader go)."""
        return bool(self.node.destroy_client(self.clients.pop(key)))

    def op_unserve(self, name: str) -> bool:
        """Destroys our server of `name` (a clean leave: its writer and reader go)."""
        return bool(self.node.destroy_service(self.services.pop(name)))

    def op_action_server(self, name: str, mode: str = "succeed", period: float = 0.05,
                         accept_after: float = 0.0) -> bool:
        """test_msgs/action/Fibonacci; mode: succeed | abort | reject | slow (cancelable).
        `accept_after`: s each goal request is held before it is answered (a busy server)."""
        from test_msgs.action import Fibonacci

        def on_goal(goal: Any) -> Any:
            time.sleep(accept_after)
            return GoalResponse.REJECT if mode == "reject" else GoalResponse.ACCEPT

        def execute(handle: Any) -> Any:
            seq = [0, 1]
            step = period * (4 if mode == "slow" else 1)
            for i in range(1, handle.request.order):
                if handle.is_cancel_requested:
                    handle.canceled()
                    return Fibonacci.Result(sequence=seq)
                seq.append(seq[i] + seq[i - 1])
                handle.publish_feedback(Fibonacci.Feedback(sequence=seq))
                time.sleep(step)
            if mode == "abort":
                handle.abort()
            else:
                handle.succeed()
            return Fibonacci.Result(sequence=seq)

        self.action_servers[name] = ActionServer(
            self.node, Fibonacci, name, execute, goal_callback=on_goal,
            cancel_callback=lambda _: CancelResponse.ACCEPT, callback_group=self.group)
        return True

    def op_action_send_goal(self, name: str, key: str, order: int) -> bool:
        """Sends a Fibonacci goal with an rclpy ActionClient; progress kept under `key`."""
        from test_msgs.action import Fibonacci

        client = self.action_clients.get(name)
        if client is None:
            client = ActionClient(self.node, Fibonacci, name, callback_group=self.group)
            self.action_clients[name] = client
        if not client.wait_for_server(timeout_sec=10.0):
            raise RuntimeError(f"no action server {name}")
        record: dict[str, Any] = {"feedback": [], "accepted": None, "result": None}
        self.goals[key] = record

        def on_feedback(msg: Any) -> None:
            with self.lock:
                record["feedback"].append(list(msg.feedback.sequence))

        def on_result(future: Any) -> None:
            res = future.result()
            with self.lock:
                record["result"] = {"status": res.status, "sequence": list(res.result.sequence)}

        def on_response(future: Any) -> None:
            handle = future.result()
            with self.lock:
                record["accepted"] = handle.accepted
            if handle.accepted:
                handle.get_result_async().add_done_callback(on_result)

        client.send_goal_async(Fibonacci.Goal(order=order), feedback_callback=on_feedback) \
            .add_done_callback(on_response)
        return True

    def op_action_goal(self, key: str, timeout: float = 20.0) -> dict[str, Any]:
        """Waits for the goal under `key` to finish (or the timeout) and returns its record."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                record = self.goals[key]
                if record["result"] is not None or record["accepted"] is False:
                    return dict(record)
            time.sleep(0.05)
        with self.lock:
            return dict(self.goals[key])


def _endpoint(info: Any) -> dict[str, Any]:
    return {
        "node_name": info.node_name,
        "node_namespace": info.node_namespace,
        "topic_type": info.topic_type,
        "type_hash": str(info.topic_type_hash),
        "reliability": info.qos_profile.reliability.name,
        "durability": info.qos_profile.durability.name,
    }


def main() -> None:
    node_name = sys.argv[1] if len(sys.argv) > 1 else "oracle"
    namespace = sys.argv[2] if len(sys.argv) > 2 else "/"
    agent = Agent(node_name, namespace)
    print(json.dumps({"id": 0, "ok": True, "result": "ready"}), flush=True)
    for line in sys.stdin:
        if not line.strip():
            continue
        request = json.loads(line)
        rid = request.pop("id")
        op = request.pop("op")
        try:
            result = getattr(agent, f"op_{op}")(**request)
            answer = {"id": rid, "ok": True, "result": result}
        except Exception as exc:  # the answer carries the failure back to the test
            answer = {"id": rid, "ok": False,
                      "error": f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"}
        print(json.dumps(answer), flush=True)
    agent.executor.shutdown()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
