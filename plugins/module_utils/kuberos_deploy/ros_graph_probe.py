"""A rollout gate's ROS-level check: are the wave's ROS 2 nodes in the graph, seen through the fleet's discovery servers?

Run by ``rosdeployment_rollout`` after a wave's soak (its ``ros_probe`` option, the ``rosdeployment_rollout_ros_probe``
role variable), on a machine that reaches the discovery servers (``ROS_DISCOVERY_SERVER`` set as the modules have it):

    python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.ros_graph_probe \\
        --expect '/{robot}/motion_planner' --timeout 10

Every ``--expect`` is a fully qualified node name; ``{robot}`` stands for each robot of the wave (``KUBEROS_ROBOTS``,
as a ROS name: ``kuberos.naming.robot_ros_name``, ``fetch-1`` is ``fetch_1``). It joins the graph as a Fast DDS
*super client* (a plain discovery-server client only learns of the participants it shares topics with), waits up to
``--timeout`` seconds for every expected node, and exits 0 when all are there, 1 (naming the missing ones) when
not, 2 on bad arguments.

With ``--absent`` instead (the rollout's update lock, docs/software.md), it waits, up to ``--timeout`` seconds, until
none of the named nodes is in the graph (after ``--settle`` seconds, so that it has heard of what is there): exit 0
when none is, 1 when some still are, printing one line ``held: <robot>`` per robot of ``KUBEROS_ROBOTS`` whose
node it still sees (``--absent '/{robot}/kuberos_update_lock'``: the robots that hold their update lock).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import sys
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import robot_ros_name
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.topics import (
    PROBE_NODE,
    Endpoint,
    Expectation,
    Observed,
    live_problems,
    missing,
    topics_to_watch,
)

UNNAMED = "_NODE_NAME_UNKNOWN_"  # what rmw reports for an endpoint whose node's name it has not heard yet
MAX_TOPICS_TEXT = 1 << 20  # KUBEROS_TOPICS or --topics-file: at most 1 MiB of JSON

_ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+\Z")


def expected_nodes(patterns: list[str], robots: list[str]) -> list[str]:
    """Fully qualified node names to look for; ``{robot}`` expands to every robot (as a ROS name)."""
    names = []
    for pattern in patterns:
        targets = [robot_ros_name(r) for r in robots] if "{robot}" in pattern else [""]
        for robot in targets:
            name = pattern.replace("{robot}", robot)
            if not _ROS_NAME.match(name):
                raise ValueError(f"{name!r} is not a fully qualified ROS node name such as /fetch_1/motion_planner")
            names.append(name)
    return sorted(set(names))


def graph_names(pairs) -> set[str]:
    """Fully qualified names of ``get_node_names_and_namespaces()`` pairs."""
    return {(namespace.rstrip("/") + "/" + name) for name, namespace in pairs}


def main(argv=None) -> int:
    # A command line program's entry point (python -m ...), not code a module runs: it prints and exits.
    # pylint: disable=ansible-bad-function
    parser = argparse.ArgumentParser(prog="ros_graph_probe", description=__doc__.split("\n\n", maxsplit=1)[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--expect", action="append", help="a node name; {robot} for each robot of the wave")
    group.add_argument("--absent", action="append", help="a node name that must not be there; {robot} for each robot")
    group.add_argument("--topics", action="store_true", help="check the declared topics of KUBEROS_TOPICS")
    group.add_argument("--topics-file", help="check the declared topics of this JSON file")
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait (default 10)")
    parser.add_argument("--settle", type=float, default=3.0, help="with --absent: seconds to listen first (default 3)")
    parser.add_argument("--window", type=float, default=3.0, help="with --topics: seconds to measure rates (default 3)")
    parser.add_argument("--json", action="store_true", help="with --topics: print what was seen as JSON")
    args = parser.parse_args(argv)
    robots = [r for r in os.environ.get("KUBEROS_ROBOTS", "").split(",") if r]
    try:
        if args.topics or args.topics_file:
            wanted = []
            declared = read_topics(args.topics_file)
        else:
            wanted = expected_nodes(args.expect or args.absent, robots)
    except ValueError as exc:
        print(f"ros_graph_probe: {exc}", file=sys.stderr)
        return 2
    if not 0 < args.timeout <= 600 or not 0 <= args.settle <= 60 or not 0 < args.window <= 60:
        print("ros_graph_probe: --timeout must be more than 0 and at most 600 s, --settle and --window at most 60 s",
              file=sys.stderr)  # fmt: skip
        return 2
    if os.environ.get("ROS_DISCOVERY_SERVER"):
        os.environ.setdefault("ROS_SUPER_CLIENT", "TRUE")  # see every participant the servers know of
    import rclpy

    rclpy.init()
    node = rclpy.create_node(PROBE_NODE)
    try:
        if args.topics or args.topics_file:
            return _check_topics(rclpy, node, topics_to_watch(declared, robots), args)
        if args.absent:
            return _wait_absent(rclpy, node, wanted, robots, args.absent, args.timeout, args.settle)
        return _wait_present(rclpy, node, wanted, args.timeout)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _wait_present(rclpy, node, wanted: list[str], timeout: float) -> int:
    # pylint: disable=ansible-bad-function
    deadline = time.monotonic() + timeout
    while True:
        seen = graph_names(node.get_node_names_and_namespaces())
        missing_nodes = [n for n in wanted if n not in seen]
        if not missing_nodes:
            print(f"ros_graph_probe: all {len(wanted)} node(s) present: {', '.join(wanted)}")
            return 0
        if time.monotonic() >= deadline:
            break
        rclpy.spin_once(node, timeout_sec=0.2)
    others = sorted(seen - {f"/{PROBE_NODE}"})
    print(
        f"ros_graph_probe: missing after {timeout:g} s: {', '.join(missing_nodes)} "
        f"(seen: {', '.join(others[:20]) or 'no other node'})",
        file=sys.stderr,
    )
    return 1


def read_topics(path: str | None, environ=None) -> list[Expectation]:
    """The declared topics to check: JSON (a list of ``Expectation.to_dict()``) from ``path`` or KUBEROS_TOPICS."""
    if path:
        try:
            with open(path, encoding="utf-8") as handle:
                text = handle.read(MAX_TOPICS_TEXT + 1)
        except OSError as exc:
            raise ValueError(f"cannot read {path}: {exc.strerror}") from None
        where = path
    else:
        text, where = (os.environ if environ is None else environ).get("KUBEROS_TOPICS", ""), "KUBEROS_TOPICS"
    if not text.strip():
        raise ValueError(f"{where} is empty; expected the declared topics as JSON")
    if len(text) > MAX_TOPICS_TEXT:
        raise ValueError(f"{where} is larger than {MAX_TOPICS_TEXT} bytes")
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"{where} is not JSON: {exc}") from None
    if not isinstance(data, list):
        raise ValueError(f"{where} is not a list of declared topics")
    wanted = []
    for position, item in enumerate(data):
        try:
            wanted.append(Expectation.from_dict(item))
        except ValueError as exc:
            raise ValueError(f"{where}[{position}]: {exc}") from None
    return wanted


_POLICIES = {"RELIABLE": "reliable", "BEST_EFFORT": "best_effort", "VOLATILE": "volatile", "TRANSIENT_LOCAL": "transient_local",
             "AUTOMATIC": "automatic", "MANUAL_BY_TOPIC": "manual_by_topic"}  # fmt: skip
# A duration this long (about 11.6 days) or longer is ROS's infinite, however the middleware spells it.
_INFINITE_NS = 10**15


def _policy(value) -> str:
    name = getattr(value, "name", str(value))
    return _POLICIES.get(name, name.lower())


def _milliseconds(duration) -> float | None:
    """An rclpy Duration in milliseconds; None for ROS's unset or infinite."""
    nanoseconds = getattr(duration, "nanoseconds", 0) or 0
    return None if nanoseconds <= 0 or nanoseconds >= _INFINITE_NS else nanoseconds / 1e6


def endpoints(infos) -> list[Endpoint]:
    """The endpoints of ``get_publishers_info_by_topic`` (or subscriptions), the probe's own left out."""
    return [
        Endpoint(
            (info.node_namespace.rstrip("/") + "/" + info.node_name),
            info.topic_type,
            _policy(info.qos_profile.reliability),
            _policy(info.qos_profile.durability),
            _milliseconds(info.qos_profile.deadline),
            _policy(info.qos_profile.liveliness),
            _milliseconds(info.qos_profile.liveliness_lease_duration),
        )
        for info in infos
        if info.node_name != PROBE_NODE
    ]


def message_class(type_name: str):
    """The Python class of ``pkg/msg/Type``, or None when its package is not installed where the probe runs."""
    package, _msg, name = type_name.partition("/msg/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None


class RateMeter:
    """Messages counted on one topic: the rate between the first and the last, or over the window."""

    def __init__(self):
        self.stamps: list[float] = []

    def __call__(self, _message) -> None:
        self.stamps.append(time.monotonic())

    def rate(self, window_s: float) -> float:
        if len(self.stamps) >= 3 and self.stamps[-1] > self.stamps[0]:
            return (len(self.stamps) - 1) / (self.stamps[-1] - self.stamps[0])
        return len(self.stamps) / window_s


def _observe(node, watched) -> dict[str, Observed]:
    return {
        name: Observed(endpoints(node.get_publishers_info_by_topic(name)), endpoints(node.get_subscriptions_info_by_topic(name)))
        for name, _want, _robot in watched
    }


def _check_topics(rclpy, node, watched, args) -> int:
    # pylint: disable=ansible-bad-function
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    started = time.monotonic()
    deadline = started + args.timeout
    while True:
        observed = _observe(node, watched)
        waiting = [line for name, want, _robot in watched for line in missing(name, want, observed[name])]
        # A participant's node names come with its discovery info, shortly after its endpoints: wait for them too.
        unnamed = any(UNNAMED in p.node for seen in observed.values() for p in (*seen.publishers, *seen.subscribers))
        if not (waiting or unnamed) or time.monotonic() >= deadline:
            break
        rclpy.spin_once(node, timeout_sec=0.2)
    discovered = time.monotonic() - started
    # Rates: a best-effort, volatile subscription matches every publisher.
    listen = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
    meters: dict[str, RateMeter] = {}
    unknown = []
    for name, want, _robot in watched:
        if (want.rate_min is None and want.rate_max is None) or not observed[name].publishers:
            continue
        kind = message_class(want.type)
        if kind is None:
            unknown.append(want.type)
            continue
        meters[name] = RateMeter()
        node.create_subscription(kind, name, meters[name], listen)
    if meters:
        end = time.monotonic() + args.window
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
    for name, meter in meters.items():
        observed[name].rate = meter.rate(args.window)
    problems = live_problems(watched, observed, args.window)
    problems += [f"rate not measured: {t} is not installed where the probe runs" for t in sorted(set(unknown))]
    took = time.monotonic() - started
    if args.json:
        print(json.dumps(_report(watched, observed, problems, discovered, took)))
    if problems:
        for line in problems:
            print(f"ros_graph_probe: {line}", file=sys.stderr)
        return 1
    robots = len({robot for _name, _want, robot in watched if robot})
    print(f"ros_graph_probe: {len(watched)} topic(s) on {robots} robot(s) as declared, in {took:.1f} s")
    return 0


def _report(watched, observed, problems, discovered_s, took_s) -> dict:
    def points(endpoints_seen):
        return [vars(point) for point in endpoints_seen]

    topics = [
        {
            "name": name,
            "robot": robot,
            "type": want.type,
            "publishers": points(observed[name].publishers),
            "subscribers": points(observed[name].subscribers),
            "rate": observed[name].rate,
        }
        for name, want, robot in watched
    ]
    return {"topics": topics, "problems": problems, "discovery_s": round(discovered_s, 3), "seconds": round(took_s, 3)}


def holders(patterns: list[str], robots: list[str], present: set[str]) -> list[str]:
    """The robots for which some ``{robot}`` pattern's node is in ``present``."""
    return [r for r in robots if any(p.replace("{robot}", robot_ros_name(r)) in present for p in patterns if "{robot}" in p)]


def _wait_absent(rclpy, node, wanted: list[str], robots: list[str], patterns: list[str], timeout: float, settle: float) -> int:
    # pylint: disable=ansible-bad-function
    start = time.monotonic()
    while True:
        seen = graph_names(node.get_node_names_and_namespaces())
        present = {n for n in wanted if n in seen}
        elapsed = time.monotonic() - start
        if not present and elapsed >= min(settle, timeout):
            print(f"ros_graph_probe: none of {len(wanted)} node(s) present after {elapsed:.1f} s")
            return 0
        if elapsed >= timeout:
            break
        rclpy.spin_once(node, timeout_sec=0.2)
    for robot in holders(patterns, robots, present):
        print(f"held: {robot}")
    print(f"ros_graph_probe: still present after {timeout:g} s: {', '.join(sorted(present))}", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())  # pylint: disable=ansible-bad-function
