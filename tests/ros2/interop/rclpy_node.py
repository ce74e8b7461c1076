"""A ROS 2 node on rclpy, driven by the interop tests through its stdin and stdout.

Run as ``python rclpy_node.py NAME [--use-sim-time]`` in the environment ``_rclpy.py`` makes
(Fast DDS on loopback, the test's domain). It reads one JSON command per line and answers each
with one JSON line, on the executor's own thread (a guard condition hands the command over),
so every rclpy call is made where the node spins:

- ``{"op": "sub", "topic": T, "type": "pkg/msg/Name", "qos": Q}``: subscribe; what arrives is
  kept (as plain values) with the node's ROS time when it arrived, and an incompatible-QoS
  event is counted;
- ``{"op": "take", "topic": T}``: the messages received since the last take;
- ``{"op": "pub", "topic": T, "type": ..., "qos": Q, "msg": {...}}``: publish one message
  (the publisher is created once per topic and kept);
- ``{"op": "now"}``: the node's clock (ns) and whether ROS time (``use_sim_time``) is active;
- ``{"op": "graph", "topics": [T, ...]}``: what ``ros2 node list`` and ``ros2 topic info -v``
  read (rclpy's graph API): nodes, and each topic's publishers and subscriptions with QoS;
- ``{"op": "matched", "topic": T}``: how many publishers the subscription of T is matched with;
- ``{"op": "events", "topic": T}``: the incompatible-QoS events of T's subscription and
  publisher, as counts and the last policy;
- ``{"op": "quit"}``.

``Q`` is ``{"reliable": bool, "transient_local": bool, "depth": int}``. It prints ``ready``
first, once the node exists.
"""

from __future__ import annotations

import importlib
import json
import queue
import sys
import threading
from typing import Any

import rclpy
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def message_type(name: str) -> Any:
    package, _, cls = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), cls)


def qos_profile(spec: dict[str, Any]) -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(spec.get("depth", 10)),
        reliability=ReliabilityPolicy.RELIABLE
        if spec.get("reliable", True)
        else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL
        if spec.get("transient_local", False)
        else DurabilityPolicy.VOLATILE,
    )


def plain(value: Any) -> Any:
    """A message as JSON values (``get_fields_and_field_types`` names the fields)."""
    if hasattr(value, "get_fields_and_field_types"):
        return {field: plain(getattr(value, field)) for field in value.get_fields_and_field_types()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


def fill(cls: Any, values: dict[str, Any]) -> Any:
    message = cls()
    types = cls.get_fields_and_field_types()
    for field, value in values.items():
        current = getattr(message, field)
        if isinstance(value, dict):
            setattr(message, field, fill(type(current), value))
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            inner = types[field].removeprefix("sequence<").removesuffix(">").replace("/", "/msg/")
            setattr(message, field, [fill(message_type(inner), v) for v in value])
        else:
            setattr(message, field, value)
    return message


def qos_info(profile: Any) -> dict[str, Any]:
    return {
        "reliability": profile.reliability.name,
        "durability": profile.durability.name,
        "history": profile.history.name,
        "depth": profile.depth,
    }


class Driven:
    def __init__(self, node: Node) -> None:
        self.node = node
        self.subs: dict[str, Any] = {}
        self.pubs: dict[str, Any] = {}
        self.received: dict[str, list[Any]] = {}
        self.events: dict[str, dict[str, Any]] = {}
        self.commands: queue.Queue[str] = queue.Queue()
        self.done = False
        self.guard = node.create_guard_condition(self.serve)

    def event(self, topic: str, side: str) -> Any:
        def record(status: Any) -> None:
            self.events.setdefault(topic, {})[side] = {
                "total_count": status.total_count,
                "last_policy_kind": status.last_policy_kind.name,
            }

        return record

    def serve(self) -> None:
        while True:
            try:
                line = self.commands.get_nowait()
            except queue.Empty:
                return
            command = json.loads(line)
            answer = getattr(self, "op_" + command.pop("op"))(**command)
            print(json.dumps(answer), flush=True)

    def op_sub(self, topic: str, type: str, qos: dict[str, Any]) -> str:
        self.received[topic] = []

        def take(message: Any) -> None:
            now = self.node.get_clock().now().nanoseconds
            self.received[topic].append({"at": now, "msg": plain(message)})

        events = SubscriptionEventCallbacks(incompatible_qos=self.event(topic, "subscription"))
        self.subs[topic] = self.node.create_subscription(
            message_type(type), topic, take, qos_profile(qos), event_callbacks=events
        )
        return "ok"

    def op_take(self, topic: str) -> list[Any]:
        taken, self.received[topic] = self.received[topic], []
        return taken

    def op_pub(self, topic: str, type: str, qos: dict[str, Any], msg: dict[str, Any]) -> str:
        cls = message_type(type)
        if topic not in self.pubs:
            events = PublisherEventCallbacks(incompatible_qos=self.event(topic, "publisher"))
            self.pubs[topic] = self.node.create_publisher(
                cls, topic, qos_profile(qos), event_callbacks=events
            )
        self.pubs[topic].publish(fill(cls, msg))
        return "ok"

    def op_now(self) -> dict[str, Any]:
        clock = self.node.get_clock()
        return {"ns": clock.now().nanoseconds, "ros_time_active": clock.ros_time_is_active}

    def op_graph(self, topics: list[str]) -> dict[str, Any]:
        node = self.node

        def endpoints(infos: Any) -> list[dict[str, Any]]:
            return [
                {
                    "node_name": info.node_name,
                    "node_namespace": info.node_namespace,
                    "topic_type": info.topic_type,
                    "qos": qos_info(info.qos_profile),
                }
                for info in infos
            ]

        return {
            "nodes": sorted(
                f"{ns.rstrip('/')}/{name}" for name, ns in node.get_node_names_and_namespaces()
            ),
            "topics": {
                topic: {
                    "publishers": endpoints(node.get_publishers_info_by_topic(topic)),
                    "subscriptions": endpoints(node.get_subscriptions_info_by_topic(topic)),
                }
                for topic in topics
            },
        }

    def op_matched(self, topic: str) -> int:
        count: int = self.subs[topic].get_publisher_count()
        return count

    def op_events(self, topic: str) -> dict[str, Any]:
        return self.events.get(topic, {})

    def op_quit(self) -> str:
        self.done = True
        return "bye"


def main() -> None:
    name = sys.argv[1]
    rclpy.init()
    overrides = [Parameter("use_sim_time", value=True)] if "--use-sim-time" in sys.argv else []
    node = Node(name, parameter_overrides=overrides)
    driven = Driven(node)
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    def read() -> None:
        for line in sys.stdin:
            driven.commands.put(line)
            driven.guard.trigger()
        driven.commands.put('{"op": "quit"}')
        driven.guard.trigger()

    threading.Thread(target=read, daemon=True).start()
    print("ready", flush=True)
    while not driven.done:
        executor.spin_once(timeout_sec=0.5)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
