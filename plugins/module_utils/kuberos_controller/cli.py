"""The controller's command line (``--help`` lists the options; docs/controller.md)::

python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller --kubeconfig FILE
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import sys

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import Settings
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import leader_election
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.controller import (
    LEASE_NAME,
    LEASE_NAMESPACE,
    Controller,
)


def build_api_client(kubeconfig: str | None):
    from kubernetes import client, config

    if kubeconfig:
        return config.new_client_from_config(config_file=kubeconfig)
    config.load_incluster_config()
    return client.ApiClient()


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="kuberos-controller",
        description="Keep every module of every RosDeployment placed well: move modules off nodes that fail, "
        "pods that keep failing and links whose measured latency breaks max_latency.",
    )
    parser.add_argument("--kubeconfig", help="kubeconfig file (default: the pod's ServiceAccount)")
    parser.add_argument("--once", action="store_true", help="run one reconcile pass and exit")
    parser.add_argument("--grace", type=float, default=Settings.grace_s, help="seconds a fault must last before modules move")
    parser.add_argument(
        "--restart-threshold", type=int, default=Settings.restart_threshold, help="restarts that count as failing"
    )
    parser.add_argument(
        "--cooldown", type=float, default=Settings.cooldown_s, help="seconds before a moved module may move again"
    )
    parser.add_argument("--resync", type=float, default=30.0, help="seconds between passes without any change")
    election = parser.add_argument_group(
        "leader election", "several replicas may run; only the holder of a coordination.k8s.io Lease acts (docs/controller.md)"
    )
    election.add_argument(
        "--no-leader-elect", dest="leader_elect", action="store_false",
        help="act without a Lease (one replica only; --once never takes one)",
    )  # fmt: skip
    election.add_argument("--lease-name", default=LEASE_NAME, help="name of the Lease (default %(default)s)")
    election.add_argument(
        "--lease-namespace", default=LEASE_NAMESPACE, help="namespace of the Lease, created when missing (default %(default)s)"
    )
    election.add_argument(
        "--lease-duration", type=float, default=leader_election.Timings.duration_s,
        help="whole seconds others wait after the last renewal they saw before taking the Lease (default %(default)g)",
    )  # fmt: skip
    election.add_argument(
        "--renew-deadline", type=float, default=leader_election.Timings.renew_deadline_s,
        help="seconds the leader acts after its last successful renewal; below --lease-duration (default %(default)g)",
    )  # fmt: skip
    election.add_argument(
        "--retry-period", type=float, default=leader_election.Timings.retry_s,
        help="seconds between tries to take or renew the Lease (default %(default)g)",
    )  # fmt: skip
    election.add_argument(
        "--identity", default=os.environ.get("POD_NAME", ""),
        help="this replica's name in the Lease (default: $POD_NAME, else host_pid)",
    )  # fmt: skip
    election.add_argument(
        "--node-name", default=os.environ.get("KUBEROS_NODE_NAME", ""),
        help="the node this replica runs on ($KUBEROS_NODE_NAME); while it is NotReady the replica does not lead",
    )  # fmt: skip
    parser.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    return parser.parse_args(argv)


def main(argv=None) -> int:
    # A command line program's entry point (python -m ...), not code a module runs: it prints and exits.
    # pylint: disable=ansible-bad-function
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(message)s", stream=sys.stderr)
    settings = Settings(grace_s=args.grace, restart_threshold=args.restart_threshold, cooldown_s=args.cooldown)
    timings = leader_election.Timings(args.lease_duration, args.renew_deadline, args.retry_period)
    if args.leader_elect and not args.once and timings.problems():
        print("kuberos-controller: " + "; ".join(timings.problems()), file=sys.stderr)
        return 2
    try:
        api_client = build_api_client(args.kubeconfig)
    except Exception as exc:
        print(f"kuberos-controller: cannot reach the cluster: {exc}", file=sys.stderr)
        return 2
    if args.once:
        Controller(api_client, settings, args.resync).run_once()
        return 0
    controller = Controller(api_client, settings, args.resync, identity=args.identity or f"{socket.gethostname()}_{os.getpid()}")
    if args.leader_elect:
        controller.elector = leader_election.LeaderElector(
            api_client, args.lease_namespace, args.lease_name, controller.identity, timings,
            on_change=lambda leading: controller.changed.set(), stand_down=lambda: controller.stand_down(args.node_name),
        )  # fmt: skip
    signal.signal(signal.SIGTERM, lambda *_: (controller.stop_event.set(), controller.changed.set()))
    signal.signal(signal.SIGINT, lambda *_: (controller.stop_event.set(), controller.changed.set()))
    controller.run()
    return 0
