"""Command line: ``python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge``.

    kuberos_bridge server --listen HOST:PORT --cert F --key F --ca F --topics F [options]
    kuberos_bridge client --connect HOST:PORT --cert F --key F --ca F --topics F [--server-name NAME] [options]
    kuberos_bridge certs --out DIR --server-name NAME [--days N] [--extra-name NAME ...]

Exit status: 0 after SIGTERM or SIGINT (a clean stop), 2 for unusable input (topics file, certificates,
an address that cannot be bound).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import signal
import ssl
import sys

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.topics import TopicsError, load_topics
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.bridge_certs import generate_certificates

# The whole file is the bridge program's command line (in its image), not code a module runs: it prints and exits.
# pylint: disable=ansible-bad-function
log = logging.getLogger("kuberos.bridge")
DEFAULT_METRICS_PORT = 9102


def _address(value: str) -> str:
    host, sep, port = value.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"{value!r} is not HOST:PORT")
    return value


def _positive(value: str) -> int:
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a whole number") from None
    if number < 1:
        raise argparse.ArgumentTypeError(f"{value!r} must be at least 1")
    return number


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="kuberos_bridge",
        description="KubeROS-Bridge: ROS 2 topics between two clusters over one mutually authenticated gRPC stream.",
    )
    commands = parser.add_subparsers(dest="command", required=True)

    def common(sub, role: str) -> None:
        sub.add_argument("--cert", required=True, help=f"this {role}'s certificate (PEM)")
        sub.add_argument("--key", required=True, help=f"this {role}'s private key (PEM)")
        sub.add_argument("--ca", required=True, help="the CA certificate the peer's certificate must be signed by (PEM)")
        sub.add_argument("--topics", required=True, help="topics file (YAML): topics: [{name, type, direction}]")
        sub.add_argument(
            "--metrics-port", type=int, default=DEFAULT_METRICS_PORT, help="HTTP port of /metrics, /healthz, /readyz (0: none)"
        )
        sub.add_argument("--metrics-host", default="0.0.0.0", help="address the HTTP endpoint listens on")
        sub.add_argument("--buffer", type=_positive, default=1000, help="messages the send buffer holds during an outage")
        sub.add_argument("--buffer-bytes", type=_positive, default=256 << 20, help="bytes the send buffer holds")
        sub.add_argument(
            "--max-message-bytes", type=_positive, default=32 << 20, help="largest serialized message sent or accepted"
        )
        sub.add_argument("--node-name", default=f"kuberos_bridge_{role}", help="name of the bridge's ROS 2 node")
        sub.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))

    server = commands.add_parser("server", help="run in the main cluster: accept the client's connection")
    server.add_argument("--listen", required=True, type=_address, help="HOST:PORT to listen on, e.g. 0.0.0.0:50051")
    common(server, "server")
    client = commands.add_parser("client", help="run beside the module in the third-party cluster: connect to the server")
    client.add_argument("--connect", required=True, type=_address, help="the server's HOST:PORT")
    client.add_argument("--server-name", help="name to expect in the server's certificate (default: HOST of --connect)")
    client.add_argument("--backoff-max", type=float, default=5.0, help="longest wait between reconnection attempts, seconds")
    common(client, "client")
    certs = commands.add_parser("certs", help="write a CA and the server's and client's certificates and keys")
    certs.add_argument(
        "--out", required=True, help="directory for ca.crt, ca.key, server.crt, server.key, client.crt, client.key"
    )
    certs.add_argument("--server-name", required=True, help="DNS name or IP address the client connects to")
    certs.add_argument("--extra-name", action="append", default=[], help="another name of the server (repeatable)")
    certs.add_argument("--days", type=_positive, default=825, help="validity of the certificates")
    return parser.parse_args(argv)


async def run(args, topics) -> int:
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.core import (
        Bridge,
        BridgeClient,
        BridgeServer,
        Settings,
        channel_credentials,
        server_credentials,
    )
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.metrics import MetricsServer
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.ros_side import RosSide

    role = args.command
    settings = Settings(max_message_bytes=args.max_message_bytes, buffer_messages=args.buffer, buffer_bytes=args.buffer_bytes)
    if role == "client":
        settings.backoff_max = max(settings.backoff_initial, args.backoff_max)
    try:
        credentials = (server_credentials if role == "server" else channel_credentials)(args.cert, args.key, args.ca)
        if role == "client":
            ssl.create_default_context(cafile=args.ca).load_cert_chain(args.cert, args.key)
    except ssl.SSLError as error:
        print(f"kuberos_bridge: the certificate, key or CA is not usable: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"kuberos_bridge: cannot read {error.filename}: {error.strerror}", file=sys.stderr)
        return 2
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    bridge = Bridge(role, topics, settings)
    bridge.bind(loop)
    metrics_server = None
    if args.metrics_port:
        try:
            metrics_server = MetricsServer(bridge, args.metrics_host, args.metrics_port)
        except OSError as error:
            print(f"kuberos_bridge: cannot serve metrics on {args.metrics_host}:{args.metrics_port}: {error}", file=sys.stderr)
            return 2
    ros = RosSide(role, topics, bridge.take, bridge.metrics, args.node_name)
    bridge.ros = ros
    ros.start()
    if metrics_server is not None:
        metrics_server.start()
    server = task = None
    status = 0
    try:
        if role == "server":
            server = BridgeServer(bridge, args.listen, credentials)
            try:
                port = await server.start()
            except (OSError, RuntimeError) as error:
                print(f"kuberos_bridge: cannot listen on {args.listen}: {error}", file=sys.stderr)
                return 2
            log.info("server listening on %s (port %d), ROS node %s (%s)", args.listen, port, args.node_name, ros.executor_name)
        else:
            server_name = args.server_name or args.connect.rpartition(":")[0].strip("[]")
            client = BridgeClient(bridge, args.connect, args.cert, args.key, args.ca, server_name)
            task = asyncio.create_task(client.run(), name="client")
            log.info(
                "client connecting to %s as %s, ROS node %s (%s)", args.connect, server_name, args.node_name, ros.executor_name
            )
        if metrics_server is not None:
            log.info("metrics on http://%s:%d/metrics", args.metrics_host, metrics_server.port)
        waiter = asyncio.create_task(stop.wait())
        done, _pending = await asyncio.wait({waiter, *([task] if task else [])}, return_when=asyncio.FIRST_COMPLETED)
        if task is not None and task in done and task.exception() is not None:
            log.error("client stopped: %r", task.exception())
            status = 1
        waiter.cancel()
    finally:
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        if server is not None:
            await server.stop()
        ros.stop()
        if metrics_server is not None:
            metrics_server.stop()
        m = bridge.metrics
        log.info(
            "stopped: %d messages sent, %d received, %d dropped, %d rejected, %d malformed frames",
            m.get("kuberos_bridge_messages_sent_total"), m.get("kuberos_bridge_messages_received_total"),
            m.get("kuberos_bridge_dropped_messages_total"), m.get("kuberos_bridge_rejected_messages_total"),
            m.get("kuberos_bridge_malformed_frames_total"),
        )  # fmt: skip
    return status


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.command == "certs":
        try:
            paths = generate_certificates(args.out, args.server_name, days=args.days, extra_server_names=args.extra_name)
        except (OSError, ValueError) as error:
            print(f"kuberos_bridge certs: {error}", file=sys.stderr)
            return 2
        print(json.dumps(paths, indent=2))
        return 0
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        topics = load_topics(args.topics)
    except TopicsError as error:
        print(f"kuberos_bridge: the topics file is not usable:\n{error}", file=sys.stderr)
        return 2
    return asyncio.run(run(args, topics))


if __name__ == "__main__":
    sys.exit(main())
