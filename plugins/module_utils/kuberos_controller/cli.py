"""The controller's command line (``--help`` lists the options; docs/controller.md)::

python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller --kubeconfig FILE
"""

from __future__ import annotations

import argparse
import logging
import os
import shlex
import signal
import socket
import sys
import threading

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.reconcile import Settings
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller import leader_election
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.burst import Burst
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.controller import (
    LEASE_NAME,
    LEASE_NAMESPACE,
    Controller,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.graph_refresh import GraphRefresh

DEFAULT_PORT = 8611


def is_loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


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
    parser.add_argument(
        "--node-probe-interval", type=float, default=1.0,
        help="seconds between the controller's probes of each edge and cloud node's kubelet port: 3 failed in a row "
        "make the node down at once, before Kubernetes' node grace period (0: Kubernetes' node status alone)",
    )  # fmt: skip
    parser.add_argument(
        "--prometheus-url",
        default="",
        help="read scaled modules' own load metrics from this Prometheus (e.g. http://prometheus:9090) instead of "
        "from each pod's /metrics",
    )
    burst = parser.add_argument_group(
        "cloud burst", "provision cloud VMs when a fleet lacks room, release them after the peak (docs/cloud.md)"
    )
    burst.add_argument(
        "--burst-command",
        default="",
        help="the provisioner to run with '-e cloud_vms_fleet=<fleet>' appended, e.g. 'ansible-playbook "
        "playbooks/cloud.yml -i inventories/local -e cloud_vms_burst=true -e cloud_vms_image_id=ami-...' (split like a "
        "shell would, run without one); empty: only the kuberos-capacity ConfigMaps are written",
    )
    burst.add_argument(
        "--burst-release-after", type=float, default=300.0,
        help="seconds without demand before the provisioner runs to release idle VMs (default %(default)s)",
    )  # fmt: skip
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
    graph = parser.add_argument_group(
        "ROS graph", "the leader checks the live ROS graph of the deployments that declare topics (the dashboard shows it)"
    )
    graph.add_argument("--graph-every", type=float, default=0.0, help="seconds between rounds of checks; 0: off (default)")
    graph.add_argument(
        "--graph-image", default="ghcr.io/kuberos/bridge:0.2.0", help="the check pod's image (rclpy and the collection)"
    )
    graph.add_argument("--graph-timeout", type=float, default=30.0, help="seconds a check waits for the declared endpoints")
    graph.add_argument("--graph-window", type=float, default=3.0, help="seconds a check measures rates over")
    view = parser.add_argument_group(
        "dashboard and /metrics", "a read-only live dashboard and Prometheus metrics (docs/dashboard.md)"
    )
    view.add_argument(
        "--dashboard-port", type=int, default=DEFAULT_PORT,
        help="port of the dashboard and /metrics (0: none; default %(default)s)",
    )  # fmt: skip
    view.add_argument(
        "--dashboard-host", default="127.0.0.1",
        help="address it listens on (default %(default)s); any other than loopback needs --dashboard-auth kubernetes",
    )  # fmt: skip
    view.add_argument(
        "--dashboard-auth", choices=("none", "kubernetes"), default=None,
        help="kubernetes: every request needs a bearer token that a TokenReview accepts and a SubjectAccessReview allows "
        "to get /kuberos/dashboard (or /metrics); default: kubernetes in a pod (no --kubeconfig), none otherwise",
    )  # fmt: skip
    view.add_argument("--dashboard-tls-cert", help="serve HTTPS with this PEM certificate (chain) ...")
    view.add_argument("--dashboard-tls-key", help="... and this PEM private key (both or neither)")
    parser.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    args = parser.parse_args(argv)
    if bool(args.dashboard_tls_cert) != bool(args.dashboard_tls_key):
        parser.error("--dashboard-tls-cert and --dashboard-tls-key go together")
    if args.dashboard_auth is None:
        args.dashboard_auth = "none" if args.kubeconfig else "kubernetes"
    if args.dashboard_port and args.dashboard_auth == "none" and not is_loopback(args.dashboard_host):
        parser.error(f"--dashboard-host {args.dashboard_host} is not a loopback address: it needs --dashboard-auth kubernetes")
    if not 0 <= args.graph_every <= 86400 or not 0 < args.graph_timeout <= 600 or not 0 < args.graph_window <= 60:
        parser.error("--graph-every is 0 to 86400 s, --graph-timeout more than 0 and at most 600, --graph-window at most 60")
    if not 0 <= args.dashboard_port <= 65535:
        parser.error(f"--dashboard-port {args.dashboard_port} is not a port (0 to 65535)")
    return args


def start_dashboard(controller, args, api_client):
    """The dashboard and /metrics, or None when off or when its port cannot be had (the controller runs on)."""
    if not args.dashboard_port:
        return None
    try:
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.auth import KubernetesAuth
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.dashboard import Dashboard

        auth = KubernetesAuth(api_client) if args.dashboard_auth == "kubernetes" else None
        tls = None
        if args.dashboard_tls_cert:
            import ssl

            tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            tls.minimum_version = ssl.TLSVersion.TLSv1_2
            tls.load_cert_chain(args.dashboard_tls_cert, args.dashboard_tls_key)
        dashboard = Dashboard(controller, args.dashboard_host, args.dashboard_port, auth, tls=tls)
        dashboard.start()
    except ImportError as exc:
        logging.getLogger("kuberos.controller").error("dashboard off: %s (install aiohttp and prometheus_client)", exc)
        return None
    except OSError as exc:  # the port is taken, or the certificate or key cannot be read (ssl.SSLError is an OSError)
        logging.getLogger("kuberos.controller").error(
            "dashboard off: cannot serve on %s:%s: %s", args.dashboard_host, args.dashboard_port, exc.strerror or exc
        )
        return None
    logging.getLogger("kuberos.controller").info(
        "dashboard on %s://%s:%d/ (metrics on /metrics, %s)", "https" if dashboard.tls else "http", args.dashboard_host,
        dashboard.port,
        "bearer tokens checked with TokenReview and SubjectAccessReview" if dashboard.auth else "no login: loopback only",
    )  # fmt: skip
    return dashboard


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
        Controller(api_client, settings, args.resync, prometheus_url=args.prometheus_url).run_once()
        return 0
    identity = args.identity or f"{socket.gethostname()}_{os.getpid()}"
    controller = Controller(
        api_client, settings, args.resync, identity=identity, prometheus_url=args.prometheus_url,
        node_probe_interval=args.node_probe_interval,
    )  # fmt: skip
    if args.leader_elect:
        controller.elector = leader_election.LeaderElector(
            api_client, args.lease_namespace, args.lease_name, controller.identity, timings,
            on_change=lambda leading: controller.changed.set(), stand_down=lambda: controller.stand_down(args.node_name),
        )  # fmt: skip
    if args.burst_command:
        controller.burst = Burst(shlex.split(args.burst_command), args.burst_release_after)
        threading.Thread(target=controller.burst.run, args=(controller.stop_event,), name="burst", daemon=True).start()
    if args.graph_every > 0:
        refresh = GraphRefresh(controller, args.graph_image, args.graph_every, args.graph_timeout, args.graph_window)
        threading.Thread(target=refresh.run, args=(controller.stop_event,), name="graph", daemon=True).start()
    dashboard = start_dashboard(controller, args, api_client)
    signal.signal(signal.SIGTERM, lambda *_: (controller.stop_event.set(), controller.changed.set()))
    signal.signal(signal.SIGINT, lambda *_: (controller.stop_event.set(), controller.changed.set()))
    controller.run()
    if dashboard is not None:
        dashboard.stop()
    return 0
