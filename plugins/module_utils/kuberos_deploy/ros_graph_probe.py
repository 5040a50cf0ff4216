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
import os
import re
import sys
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import robot_ros_name

_ROS_NAME = re.compile(r"^(/[A-Za-z_][A-Za-z0-9_]*)+$")


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
    parser.add_argument("--timeout", type=float, default=10.0, help="seconds to wait (default 10)")
    parser.add_argument("--settle", type=float, default=3.0, help="with --absent: seconds to listen first (default 3)")
    args = parser.parse_args(argv)
    robots = [r for r in os.environ.get("KUBEROS_ROBOTS", "").split(",") if r]
    try:
        wanted = expected_nodes(args.expect or args.absent, robots)
    except ValueError as exc:
        print(f"ros_graph_probe: {exc}", file=sys.stderr)
        return 2
    if not 0 < args.timeout <= 600 or not 0 <= args.settle <= 60:
        print("ros_graph_probe: --timeout must be more than 0 and at most 600 s, --settle at most 60 s", file=sys.stderr)
        return 2
    if os.environ.get("ROS_DISCOVERY_SERVER"):
        os.environ.setdefault("ROS_SUPER_CLIENT", "TRUE")  # see every participant the servers know of
    import rclpy

    rclpy.init()
    node = rclpy.create_node("kuberos_rollout_probe")
    if args.absent:
        try:
            return _wait_absent(rclpy, node, wanted, robots, args.absent, args.timeout, args.settle)
        finally:
            node.destroy_node()
            rclpy.try_shutdown()
    seen: set[str] = set()
    try:
        deadline = time.monotonic() + args.timeout
        while True:
            seen = graph_names(node.get_node_names_and_namespaces())
            missing = [n for n in wanted if n not in seen]
            if not missing:
                print(f"ros_graph_probe: all {len(wanted)} node(s) present: {', '.join(wanted)}")
                return 0
            if time.monotonic() >= deadline:
                break
            rclpy.spin_once(node, timeout_sec=0.2)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    others = sorted(seen - {"/kuberos_rollout_probe"})
    print(
        f"ros_graph_probe: missing after {args.timeout:g} s: {', '.join(missing)} "
        f"(seen: {', '.join(others[:20]) or 'no other node'})",
        file=sys.stderr,
    )
    return 1


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
