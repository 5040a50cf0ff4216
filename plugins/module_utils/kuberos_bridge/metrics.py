"""Counters and gauges of a bridge, served as Prometheus text on /metrics, with /healthz and /readyz.

- /healthz: 200 while the process runs its ROS node and its gRPC side (JSON: role, connected, peer, buffer);
- /readyz: 200 only while connected to the peer, 503 otherwise;
- /metrics: the families in ``HELP`` below, per topic and direction where they concern messages.
"""

from __future__ import annotations

import http.server
import json
import threading
import time

HELP = {
    "kuberos_bridge_messages_sent_total": ("counter", "Messages written to the stream to the peer."),
    "kuberos_bridge_bytes_sent_total": ("counter", "Serialized message bytes written to the stream to the peer."),
    "kuberos_bridge_messages_received_total": ("counter", "Messages received from the peer and published in ROS."),
    "kuberos_bridge_bytes_received_total": ("counter", "Serialized message bytes received from the peer and published."),
    "kuberos_bridge_dropped_messages_total": (
        "counter",
        "Messages this bridge took from ROS but never sent: buffer_full (the oldest went while the buffer was full, "
        "e.g. during an outage), oversized (larger than --max-message-bytes or the peer's limit).",
    ),
    "kuberos_bridge_rejected_messages_total": (
        "counter",
        "Messages from the peer not published: unknown_topic, wrong_direction, type_mismatch, topic_disabled, "
        "oversized, bad_cdr, publish_failed.",
    ),
    "kuberos_bridge_sequence_gaps_total": (
        "counter",
        "Messages missing in the peer's per-topic sequence (dropped by the peer or lost with a broken connection).",
    ),
    "kuberos_bridge_malformed_frames_total": ("counter", "Frames from the peer that are not valid bridge frames."),
    "kuberos_bridge_connections_total": ("counter", "Sessions established with a peer (Hello exchanged)."),
    "kuberos_bridge_reconnects_total": ("counter", "Sessions established after an earlier session ended."),
    "kuberos_bridge_disconnects_total": ("counter", "Sessions that ended."),
    "kuberos_bridge_connect_failures_total": ("counter", "Connection attempts that failed, by reason (tls, unavailable, ...)."),
    "kuberos_bridge_topic_errors_total": ("counter", "Topics disabled or not subscribed, by reason (unknown_type, ...)."),
    "kuberos_bridge_connected": ("gauge", "1 while a session with the peer is up."),
    "kuberos_bridge_buffered_messages": ("gauge", "Messages waiting in the send buffer."),
    "kuberos_bridge_buffered_bytes": ("gauge", "Bytes waiting in the send buffer."),
    "kuberos_bridge_topic_active": ("gauge", "1 when the topic is subscribed (outgoing) or has a publisher (incoming)."),
}


def _escape(value: str) -> str:
    return str(value).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


class Metrics:
    def __init__(self):
        self._lock = threading.Lock()
        self._values: dict[tuple[str, tuple[tuple[str, str], ...]], float] = {}
        self._gauges: dict[str, callable] = {}  # name -> function returning the value, read at scrape time
        self.hooks: list = []  # functions that update values, run before every read

    def inc(self, name: str, value: float = 1, **labels: str) -> None:
        key = (name, tuple(sorted(labels.items())))
        with self._lock:
            self._values[key] = self._values.get(key, 0) + value

    def set(self, name: str, value: float, **labels: str) -> None:
        key = (name, tuple(sorted(labels.items())))
        with self._lock:
            self._values[key] = value

    def gauge_function(self, name: str, function) -> None:
        self._gauges[name] = function

    def _run_hooks(self) -> None:
        for hook in self.hooks:
            hook()

    def get(self, name: str, **labels: str) -> float:
        self._run_hooks()
        with self._lock:
            if labels:
                return self._values.get((name, tuple(sorted(labels.items()))), 0)
            return sum(v for (n, _labels), v in self._values.items() if n == name)

    def render(self) -> str:
        self._run_hooks()
        with self._lock:
            values = dict(self._values)
        for name, function in self._gauges.items():
            try:
                values[(name, ())] = function()
            except Exception:  # a gauge must never break a scrape
                continue
        by_name: dict[str, list[tuple[tuple[tuple[str, str], ...], float]]] = {}
        for (name, labels), value in values.items():
            by_name.setdefault(name, []).append((labels, value))
        lines = []
        for name in sorted(set(HELP) | set(by_name)):
            kind, text = HELP.get(name, ("untyped", ""))
            lines.append(f"# HELP {name} {text}")
            lines.append(f"# TYPE {name} {kind}")
            for labels, value in sorted(by_name.get(name, [])):
                rendered = ",".join(f'{k}="{_escape(v)}"' for k, v in labels)
                number = int(value) if float(value).is_integer() else value
                lines.append(f"{name}{{{rendered}}} {number}" if rendered else f"{name} {number}")
        return "\n".join(lines) + "\n"


class _Handler(http.server.BaseHTTPRequestHandler):
    server_version = "kuberos-bridge"

    def do_GET(self):
        bridge = self.server.bridge
        path = self.path.split("?", 1)[0]
        if path == "/metrics":
            body, status, kind = bridge.metrics.render().encode(), 200, "text/plain; version=0.0.4; charset=utf-8"
        elif path in ("/healthz", "/readyz"):
            state = bridge.health()
            ok = state["healthy"] if path == "/healthz" else state["connected"]
            body, status, kind = (json.dumps(state) + "\n").encode(), 200 if ok else 503, "application/json"
        else:
            body, status, kind = b"not found: /metrics, /healthz, /readyz\n", 404, "text/plain"
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):  # scrapes are not worth a log line each
        pass


class MetricsServer:
    """The HTTP endpoint in a daemon thread; ``bridge`` has ``metrics`` and ``health()``."""

    def __init__(self, bridge, host: str, port: int):
        self.httpd = http.server.ThreadingHTTPServer((host, port), _Handler)
        self.httpd.daemon_threads = True
        self.httpd.bridge = bridge
        self.port = self.httpd.server_address[1]
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True)
        self.started = time.time()

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
