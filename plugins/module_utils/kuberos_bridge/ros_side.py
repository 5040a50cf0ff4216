"""The bridge's ROS 2 node: raw subscriptions to the outgoing topics, raw publishers of the incoming ones.

The node spins in a thread of its own (rclpy's EventsExecutor when this rclpy has it: about ten times
the callback rate of the SingleThreadedExecutor, which is the fallback). Every outgoing topic waits for
its first publisher: then the node subscribes with ``raw=True`` (the message stays CDR bytes) and the QoS
those publishers offer (best effort if any of them is, transient local if all of them are), and
re-subscribes when that changes. Incoming messages are published as CDR bytes by a publisher created on
the first message of a topic with the QoS the far side reported, created again when that QoS changes.
"""

from __future__ import annotations

import collections
import concurrent.futures
import logging
import os
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.envelope import (
    BEST_EFFORT,
    RELIABLE,
    TRANSIENT_LOCAL,
    VOLATILE,
    Qos,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.topics import (
    Topic,
    TypeLookupError,
    load_message_type,
)

log = logging.getLogger("kuberos.bridge.ros")
SUBSCRIPTION_HISTORY = 1000  # the bridge's subscriptions keep this many messages (or the depth) while its thread is busy
PUBLISHER_HISTORY = 1000
PUBLISHER_HISTORY_BYTES = 64 << 20


def qos_profile(qos: Qos, depth: int | None = None):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth or qos.depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if qos.reliability == BEST_EFFORT else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if qos.durability == TRANSIENT_LOCAL else DurabilityPolicy.VOLATILE,
    )


def publishers_qos(infos, depth: int) -> Qos:
    """The QoS a subscription needs to match every publisher and get what they keep for late joiners."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
    transient = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
    return Qos(BEST_EFFORT if best_effort else RELIABLE, TRANSIENT_LOCAL if transient else VOLATILE, depth)


def publisher_history(qos: Qos, message_bytes: int) -> int:
    """History depth of the bridge's publisher: the publishers' depth, or more for a volatile topic.

    The bridge hands a subscriber the messages in bursts (a frame at a time, the backlog after an outage), so
    a volatile topic's history holds up to PUBLISHER_HISTORY messages and PUBLISHER_HISTORY_BYTES bytes,
    never less than the depth; a subscriber sees no difference but fewer losses. A transient-local topic keeps
    exactly its depth: that is what a late subscriber receives.
    """
    if qos.durability == TRANSIENT_LOCAL:
        return qos.depth
    by_bytes = PUBLISHER_HISTORY_BYTES // max(1, message_bytes)
    return max(qos.depth, min(PUBLISHER_HISTORY, by_bytes))


class RosSide:
    """``on_message(topic, qos, cdr, source_ns)`` is called in the ROS thread for every outgoing message."""

    def __init__(self, role: str, topics: list[Topic], on_message, metrics, node_name: str, poll_period: float = 0.5):
        self.role, self.on_message, self.metrics = role, on_message, metrics
        self.node_name, self.poll_period = node_name, poll_period
        self.outgoing = [t for t in topics if t.outgoing_for(role)]
        self.incoming = {t.name: t for t in topics if not t.outgoing_for(role)}
        self.types: dict[str, type] = {}
        self.disabled: dict[str, str] = {}  # topic -> why it is not bridged
        self.subscriptions: dict[str, tuple[Qos, object]] = {}
        self.publishers: dict[str, tuple[Qos, object]] = {}
        self._reported: dict[str, str] = {}
        self._actions: collections.deque = collections.deque()
        self._stopping = threading.Event()
        self.thread: threading.Thread | None = None
        self.executor_name = ""
        self.started_at = time.monotonic()
        self.node = self.context = self.executor = None

    # -- life cycle -----------------------------------------------------------------------------
    def start(self) -> None:
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        for topic in [*self.outgoing, *self.incoming.values()]:
            try:
                self.types[topic.name] = load_message_type(topic.type)
                self.metrics.set("kuberos_bridge_topic_active", 0, topic=topic.name, direction=topic.direction)
            except TypeLookupError as error:
                self.disabled[topic.name] = str(error)
                self.metrics.inc("kuberos_bridge_topic_errors_total", topic=topic.name, reason="unknown_type")
                self.metrics.set("kuberos_bridge_topic_active", 0, topic=topic.name, direction=topic.direction)
                log.error("topic %s is not bridged: %s", topic.name, error)
        # With ROS_DISCOVERY_SERVER a plain client participant learns only of endpoints on its own topics, so the
        # bridge would never see the publishers it waits for: it is a super client (Fast DDS) unless told otherwise.
        if os.environ.get("ROS_DISCOVERY_SERVER") and "ROS_SUPER_CLIENT" not in os.environ:
            os.environ["ROS_SUPER_CLIENT"] = "TRUE"
        self.started_at = time.monotonic()
        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(self.node_name, context=self.context)
        try:
            from rclpy.experimental import EventsExecutor

            self.executor = EventsExecutor(context=self.context)
            self.executor_name = "EventsExecutor"
        except ImportError:
            from rclpy.executors import SingleThreadedExecutor

            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor_name = "SingleThreadedExecutor"
        self.executor.add_node(self.node)
        self.node.create_timer(self.poll_period, self._guarded(self._poll_publishers))
        self.thread = threading.Thread(target=self._spin, name="ros", daemon=True)
        self.thread.start()
        self.call(self._poll_publishers)

    def _spin(self) -> None:
        while not self._stopping.is_set():
            try:
                self.executor.spin_once(timeout_sec=0.2)
            except Exception as error:  # a callback's error must not end the node
                if self._stopping.is_set():
                    break
                log.exception("ROS executor: %s", error)
                time.sleep(0.05)

    def subscribers(self, topic: Topic, publisher) -> tuple[int, int]:
        """(subscriptions matched with publisher, subscriptions of the topic the graph knows of)."""
        return publisher.get_subscription_count(), self.node.count_subscribers(topic.name)

    def alive(self) -> bool:
        return self.thread is not None and self.thread.is_alive()

    def stop(self) -> None:
        import rclpy

        self._stopping.set()
        if self.thread is not None:
            self.thread.join(5.0)
        try:
            if self.executor is not None:
                self.executor.shutdown()
            if self.node is not None:
                self.node.destroy_node()
        finally:
            if self.context is not None:
                rclpy.try_shutdown(context=self.context)

    # -- work in the ROS thread ------------------------------------------------------------------
    def call(self, function) -> concurrent.futures.Future:
        """Run function in the ROS thread; a Future of its result."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        self._actions.append((function, future))
        self.executor.create_task(self._run_actions)  # thread-safe in both executors; wakes the spinning thread
        return future

    def _run_actions(self) -> None:
        while self._actions:
            function, future = self._actions.popleft()
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(function())
            except Exception as error:
                future.set_exception(error)

    @staticmethod
    def _guarded(function):
        def run():
            try:
                function()
            except Exception:
                log.exception("%s failed", function.__name__)

        return run

    def _report_once(self, topic: str, text: str, reason: str) -> None:
        if self._reported.get(topic) != text:
            self._reported[topic] = text
            self.metrics.inc("kuberos_bridge_topic_errors_total", topic=topic, reason=reason)
            log.error("%s", text)

    def _poll_publishers(self) -> None:
        """(Re)subscribe every outgoing topic that has publishers, with the QoS they offer."""
        for topic in self.outgoing:
            if topic.name in self.disabled:
                continue
            infos = self.node.get_publishers_info_by_topic(topic.name)
            if not infos:
                continue
            matching = [i for i in infos if i.topic_type == topic.type]
            if not matching:
                types = ", ".join(sorted({i.topic_type for i in infos}))
                self._report_once(
                    topic.name,
                    f"topic {topic.name}: its publishers have type {types}, the topics file says {topic.type}; not subscribed",
                    "type_mismatch",
                )
                continue
            qos = publishers_qos(matching, topic.depth)
            current = self.subscriptions.get(topic.name)
            if current is not None and current[0] == qos:
                continue
            if current is not None:
                self.node.destroy_subscription(current[1])
            subscription = self.node.create_subscription(
                self.types[topic.name], topic.name, self._callback(topic, qos),
                qos_profile(qos, max(qos.depth, SUBSCRIPTION_HISTORY)), raw=True,
            )  # fmt: skip
            self.subscriptions[topic.name] = (qos, subscription)
            self._reported.pop(topic.name, None)
            self.metrics.set("kuberos_bridge_topic_active", 1, topic=topic.name, direction=topic.direction)
            log.info(
                "%s topic %s (%s): subscribed, %s/%s depth %d, %d publisher(s)",
                "re-subscribed" if current else "outgoing", topic.name, topic.type,
                qos.reliability, qos.durability, qos.depth, len(matching),
            )  # fmt: skip

    def _callback(self, topic: Topic, qos: Qos):
        """The subscription's callback. rclpy passes message info (the publisher's source timestamp) to a callback
        of two arguments, but Jazzy's EventsExecutor fails on those: with it the source timestamp stays 0."""
        on_message = self.on_message
        if self.executor_name == "EventsExecutor":

            def take(cdr):
                on_message(topic, qos, cdr, 0)

            return take

        def take_with_info(cdr, info):
            source = int(info.get("source_timestamp") or 0) if isinstance(info, dict) else 0
            on_message(topic, qos, cdr, source)

        return take_with_info

    # -- publishing (any thread) -----------------------------------------------------------------
    def publisher(self, topic: Topic, qos: Qos):
        """The publisher of an incoming topic if it exists with this QoS, else None (see create_publisher)."""
        current = self.publishers.get(topic.name)
        return current[1] if current is not None and current[0] == qos else None

    def create_publisher(self, topic: Topic, qos: Qos, message_bytes: int = 0) -> concurrent.futures.Future:
        """Create (or re-create with a new QoS) the publisher of an incoming topic, in the ROS thread."""
        depth = publisher_history(qos, message_bytes)

        def create():
            current = self.publishers.get(topic.name)
            if current is not None and current[0] == qos:
                return current[1]
            if current is not None:
                self.node.destroy_publisher(current[1])
            publisher = self.node.create_publisher(self.types[topic.name], topic.name, qos_profile(qos, depth))
            self.publishers[topic.name] = (qos, publisher)
            self.metrics.set("kuberos_bridge_topic_active", 1, topic=topic.name, direction=topic.direction)
            log.info(
                "incoming topic %s (%s): publishing, %s/%s depth %d (history %d)",
                topic.name, topic.type, qos.reliability, qos.durability, qos.depth, depth,
            )  # fmt: skip
            return publisher

        return self.call(create)
