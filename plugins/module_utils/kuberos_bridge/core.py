"""The bridge: a session over one gRPC bidirectional stream, the server and the client around it.

A session starts with Hello frames both ways (the client's first), then two tasks run until the stream
ends: the sender writes Batches from the send buffer, the receiver checks every Envelope and publishes it
in ROS. The server keeps one session at a time (a new connection replaces the old one: a client that
reconnects before the server noticed the old stream is gone). The client reconnects with exponential
backoff; a TLS or authentication failure is reported as such. Bad input from the peer (a frame that does
not parse, an unknown topic, a type other than the topics file's, an oversized message, bytes that are
not CDR) is counted and logged, rate-limited, and never ends the process.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from dataclasses import dataclass

try:
    import grpc
except ImportError:  # the bridge's image has grpcio; without it this still imports (ansible-test's import check)
    grpc = None

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.buffer import Backoff, DropOldestBuffer, Outgoing
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.envelope import (
    METHOD,
    PROTOCOL,
    FrameError,
    Qos,
    batch_frame,
    cdr_problem,
    decode_frame,
    hello_frame,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.metrics import Metrics
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.topics import Topic

log = logging.getLogger("kuberos.bridge")

SERVICE, EXCHANGE = METHOD.strip("/").split("/")
MAX_BATCH_MESSAGES = 512
MAX_BATCH_BYTES = 1 << 20
FRAME_HEADROOM = 2 << 20  # a frame is at most one message (up to max_message_bytes) or a batch of 1 MiB, plus envelopes
LINGER = 0.001  # seconds a frame waits for more messages when frames follow each other closely
LINGER_WHEN_WITHIN = 0.002  # "closely": the previous frame was written less than this many seconds ago
LINGER_BELOW = 64  # a batch of this many messages already is sent at once
LOG_EVERY = 10.0  # seconds between repeated log lines of one kind
MATCH_WAIT = 3.0  # seconds a new publisher waits for the topic's subscribers to match it
MATCH_GRACE = 2.0  # and then for them to have matched it in turn (discovery through a server takes a while)
BACKLOG_NS = 500_000_000  # a message taken from ROS by the peer longer ago than this is backlog
REPLAY_SPEEDUP = 2.0  # a backlog is published at twice the pace the peer took it from ROS
MAX_REPLAY_GAP = 1.0  # seconds between two backlog messages at most
GRAPH_SETTLE = 3.0  # seconds after the node started during which the graph may not know every subscriber yet
PROBE_WORDS = ("socket closed", "connection reset", "end of file", "eof")  # a TLS 1.3 refusal, seen by gRPC
TLS_WORDS = ("ssl", "tls", "handshake", "certificate", "x509", "alert", "peer did not return a certificate")


@dataclass
class Settings:
    max_message_bytes: int = 32 << 20
    buffer_messages: int = 1000
    buffer_bytes: int = 256 << 20
    hello_timeout: float = 10.0
    backoff_initial: float = 0.1
    backoff_max: float = 5.0
    keepalive_s: float = 10.0


def grpc_options(settings: Settings) -> list[tuple[str, int]]:
    frame_limit = settings.max_message_bytes + FRAME_HEADROOM
    return [
        ("grpc.max_send_message_length", frame_limit),
        ("grpc.max_receive_message_length", frame_limit),
        ("grpc.keepalive_time_ms", int(settings.keepalive_s * 1000)),
        ("grpc.keepalive_timeout_ms", 5000),
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.max_pings_without_data", 0),
        ("grpc.http2.min_recv_ping_interval_without_data_ms", 5000),
        ("grpc.http2.max_ping_strikes", 0),  # the peer is authenticated; never answer its keepalive with GOAWAY
        ("grpc.http2.lookahead_bytes", 8 << 20),  # receive window: a 1 MB message should not wait for window updates
    ]


def failure_reason(error: BaseException) -> str:
    """tls, unavailable, timeout, protocol or the gRPC status code name, for metrics and logs."""
    if isinstance(error, grpc.aio.AioRpcError):
        details = (error.details() or "").lower()
        debug = (error.debug_error_string() or "").lower()
        if any(word in details or word in debug for word in TLS_WORDS):
            return "tls"
        return error.code().name.lower()
    if isinstance(error, TimeoutError | asyncio.TimeoutError):
        return "timeout"
    if isinstance(error, FrameError | ProtocolError):
        return "protocol"
    return type(error).__name__


def describe(error: BaseException) -> str:
    if isinstance(error, grpc.aio.AioRpcError):
        return f"{error.code().name}: {error.details()}"
    return f"{type(error).__name__}: {error}" if str(error) else type(error).__name__


class ProtocolError(Exception):
    """The peer broke the bridge protocol (no Hello first, another protocol version, ...)."""


class RateLimitedLog:
    """One line per key at most every LOG_EVERY seconds, with how many were suppressed in between."""

    def __init__(self):
        self._last: dict[str, tuple[float, int]] = {}

    def __call__(self, level: int, key: str, message: str, *args) -> None:
        now = time.monotonic()
        last, suppressed = self._last.get(key, (-LOG_EVERY, 0))
        if now - last >= LOG_EVERY:
            suffix = f" ({suppressed} more like this since the last line)" if suppressed else ""
            log.log(level, message + suffix, *args)
            self._last[key] = (now, 0)
        else:
            self._last[key] = (last, suppressed + 1)


class Bridge:
    """What the server and the client share: the topics, the send buffer, the metrics and one session."""

    def __init__(self, role: str, topics: list[Topic], settings: Settings):
        self.role, self.settings = role, settings
        self.topics = {t.name: t for t in topics}
        self.metrics = Metrics()
        self.buffer = DropOldestBuffer(settings.buffer_messages, settings.buffer_bytes)
        self.session = secrets.token_hex(8)
        self.ros = None  # RosSide (or a stand-in with publisher/create_publisher/disabled/alive)
        self.loop: asyncio.AbstractEventLoop | None = None
        self.connected = False
        self.peer = ""
        self.peer_max = settings.max_message_bytes
        self.peer_session = ""
        self.sessions = 0
        self.disconnected_at = time.monotonic()
        self._wake: asyncio.Event | None = None
        self._sequences = {name: 0 for name in self.topics}
        self._peer_sequences: dict[str, int] = {}
        self._replays: dict[str, tuple[float, int]] = {}  # topic -> (local time, peer's take time) of a backlog's start
        self._limited = RateLimitedLog()
        self._outage_logged = False
        self.metrics.set("kuberos_bridge_connected", 0)
        self.metrics.gauge_function("kuberos_bridge_buffered_messages", lambda: len(self.buffer))
        self.metrics.gauge_function("kuberos_bridge_buffered_bytes", lambda: self.buffer.bytes)
        self.metrics.hooks.append(self.collect_drops)

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._wake = asyncio.Event()
        self.buffer.waker = lambda: loop.call_soon_threadsafe(self._wake.set)

    def health(self) -> dict:
        ros_ok = self.ros is None or self.ros.alive()
        loop_ok = self.loop is not None and not self.loop.is_closed()
        return {
            "healthy": bool(ros_ok and loop_ok),
            "role": self.role,
            "connected": self.connected,
            "peer": self.peer,
            "buffered_messages": len(self.buffer),
            "sessions": self.sessions,
            "disabled_topics": sorted(getattr(self.ros, "disabled", {}) or {}),
        }

    # -- from ROS (the ROS thread) -----------------------------------------------------------------
    def take(self, topic: Topic, qos: Qos, cdr: bytes, source_ns: int = 0) -> None:
        """A message of an outgoing topic, from ROS: into the send buffer (dropping the oldest when full)."""
        if len(cdr) > min(self.settings.max_message_bytes, self.peer_max):
            self.metrics.inc(
                "kuberos_bridge_dropped_messages_total", topic=topic.name, direction=topic.direction, reason="oversized"
            )
            self._limited(
                logging.ERROR, f"oversized {topic.name}",
                "%s: dropped a message of %d bytes, larger than the limit of %d bytes (--max-message-bytes here or at the peer)",
                topic.name, len(cdr), min(self.settings.max_message_bytes, self.peer_max),
            )  # fmt: skip
            return
        self._sequences[topic.name] += 1
        item = Outgoing(topic.name, topic.type, cdr, self._sequences[topic.name], source_ns, time.time_ns(), qos)
        if self.buffer.push(item):
            self._count_drops()

    def _count_drops(self) -> None:
        if not self._outage_logged:
            self._outage_logged = True
            log.warning(
                "send buffer full (%d messages / %d bytes at most)%s: dropping the oldest messages",
                self.buffer.max_messages, self.buffer.max_bytes, "" if self.connected else " while the peer is not connected",
            )  # fmt: skip
        self._limited(logging.WARNING, "dropping", "still dropping: %s", self._drops_text(self.buffer.dropped, "since start"))

    @staticmethod
    def _drops_text(drops: dict[str, int], when: str) -> str:
        return ", ".join(f"{topic} {count}" for topic, count in sorted(drops.items())) + f" dropped {when}"

    def collect_drops(self) -> None:
        """Copy the buffer's per-topic drop counts into the metrics (called before a scrape and on events)."""
        for topic, count in self.buffer.dropped.items():
            direction = self.topics[topic].direction if topic in self.topics else ""
            self.metrics.set(
                "kuberos_bridge_dropped_messages_total", count, topic=topic, direction=direction, reason="buffer_full"
            )

    # -- a session ---------------------------------------------------------------------------------
    def _started(self, hello, peer: str) -> None:
        self.sessions += 1
        self.connected, self.peer = True, peer
        self.peer_max = hello.max_message_bytes or self.settings.max_message_bytes
        if hello.session != self.peer_session:
            self._peer_sequences.clear()
            self.peer_session = hello.session
        self.metrics.inc("kuberos_bridge_connections_total")
        if self.sessions > 1:
            self.metrics.inc("kuberos_bridge_reconnects_total")
        self.metrics.set("kuberos_bridge_connected", 1)
        self.collect_drops()
        drops = self.buffer.take_report()
        outage = time.monotonic() - self.disconnected_at
        self._outage_logged = False
        log.info(
            "connected to %s %s (session %s, %s); %s; %d buffered messages to send",
            hello.role or "peer", peer, self.sessions,
            "first session" if self.sessions == 1 else f"after {outage:.1f} s without a session",
            self._drops_text(drops, "while disconnected") if drops else "nothing dropped while disconnected",
            len(self.buffer),
        )  # fmt: skip
        theirs = {(t.name, t.type, t.direction) for t in hello.topics}
        ours = {(t.name, t.type, t.direction) for t in self.topics.values()}
        if theirs != ours:
            log.warning(
                "the peer's topics differ from ours: only here %s; only there %s",
                sorted(ours - theirs) or "none", sorted(theirs - ours) or "none",
            )  # fmt: skip

    def _ended(self, reason: str) -> None:
        self.connected = False
        self.disconnected_at = time.monotonic()
        self.metrics.inc("kuberos_bridge_disconnects_total")
        self.metrics.set("kuberos_bridge_connected", 0)
        log.warning("session %d with %s ended: %s", self.sessions, self.peer, reason)

    async def run_session(self, hello, peer: str, read, write) -> str:
        """Send and receive until the stream ends; returns why it ended."""
        self._started(hello, peer)
        sender = asyncio.create_task(self._send_loop(write), name="send")
        receiver = asyncio.create_task(self._receive_loop(read), name="receive")
        reason = "stopped"
        try:
            done, _pending = await asyncio.wait({sender, receiver}, return_when=asyncio.FIRST_COMPLETED)
            task = done.pop()
            error = task.exception()
            if error is None:
                reason = "the peer closed the stream"
            else:
                reason = describe(error)
        finally:
            for task in (sender, receiver):
                task.cancel()
            await asyncio.gather(sender, receiver, return_exceptions=True)
            self._ended(reason)
        return reason

    async def _send_loop(self, write) -> None:
        last_write = 0.0
        while True:
            self._wake.clear()
            batch = self.buffer.pop_batch(MAX_BATCH_MESSAGES, MAX_BATCH_BYTES)
            if not batch:
                await self._wake.wait()
                continue
            if time.monotonic() - last_write < LINGER_WHEN_WITHIN and len(batch) < LINGER_BELOW:
                # Frames are following each other closely: a busy topic. Waiting LINGER s lets the next messages
                # join this frame (fewer, larger frames cost much less per message); a quiet topic never waits.
                await asyncio.sleep(LINGER)
                size = sum(len(item.cdr) for item in batch)
                batch += self.buffer.pop_batch(MAX_BATCH_MESSAGES - len(batch), max(1, MAX_BATCH_BYTES - size))
            limit = min(self.settings.max_message_bytes, self.peer_max)
            sendable = [item for item in batch if len(item.cdr) <= limit]
            for item in batch:
                if len(item.cdr) > limit:
                    topic = self.topics[item.topic]
                    self.metrics.inc(
                        "kuberos_bridge_dropped_messages_total", topic=item.topic, direction=topic.direction, reason="oversized"
                    )
                    self._limited(
                        logging.ERROR,
                        f"oversized {item.topic}",
                        "%s: dropped a message of %d bytes, the peer takes at most %d",
                        item.topic,
                        len(item.cdr),
                        limit,
                    )
            if not sendable:
                continue
            frame = batch_frame(sendable)
            try:
                await write(frame)
            except BaseException:
                if self.buffer.requeue(sendable):
                    self._count_drops()
                raise
            last_write = time.monotonic()
            counts: dict[str, list[int]] = {}
            for item in sendable:
                entry = counts.setdefault(item.topic, [0, 0])
                entry[0] += 1
                entry[1] += len(item.cdr)
            for topic, (messages, size) in counts.items():
                direction = self.topics[topic].direction
                self.metrics.inc("kuberos_bridge_messages_sent_total", messages, topic=topic, direction=direction)
                self.metrics.inc("kuberos_bridge_bytes_sent_total", size, topic=topic, direction=direction)

    async def _receive_loop(self, read) -> None:
        while True:
            data = await read()
            if data is grpc.aio.EOF:
                return
            try:
                frame = decode_frame(data)
            except FrameError as error:
                self.metrics.inc("kuberos_bridge_malformed_frames_total")
                self._limited(logging.ERROR, "malformed", "malformed frame from %s ignored: %s", self.peer, error)
                continue
            if frame.WhichOneof("body") != "batch":
                self.metrics.inc("kuberos_bridge_malformed_frames_total")
                self._limited(
                    logging.ERROR, "hello again", "unexpected Hello from %s in the middle of a session ignored", self.peer
                )
                continue
            for envelope in frame.batch.envelopes:
                await self.deliver(envelope)

    def _reject(self, envelope, topic_label: str, direction: str, reason: str, why: str) -> None:
        self.metrics.inc("kuberos_bridge_rejected_messages_total", topic=topic_label, direction=direction, reason=reason)
        self._limited(
            logging.ERROR,
            f"reject {topic_label} {reason}",
            "message on %s from the peer not published: %s",
            envelope.topic[:200],
            why,
        )

    async def _let_subscribers_match(self, topic: Topic, publisher) -> None:
        """Wait (at most MATCH_WAIT s) before a new publisher's first message, so that subscribers get it.

        A volatile message reaches only subscriptions already matched with the publisher. Subscriptions the graph
        knows of match within milliseconds; right after the bridge started (GRAPH_SETTLE s) the graph itself may
        not know them yet. Only this topic's delivery waits; the stream's order is kept.
        """
        subscribers = getattr(self.ros, "subscribers", None)
        if subscribers is None:
            return
        deadline = time.monotonic() + MATCH_WAIT
        settled_at = getattr(self.ros, "started_at", 0.0) + GRAPH_SETTLE
        while time.monotonic() < deadline:
            matched, known = subscribers(topic, publisher)
            if known and matched >= known:
                # The writer has matched the readers; the readers may match the writer a little later, and a
                # volatile reader ignores what was written before. MATCH_GRACE covers that.
                await asyncio.sleep(MATCH_GRACE)
                return
            if not known and time.monotonic() >= settled_at:
                return
            await asyncio.sleep(0.01)

    async def _replay(self, topic: Topic, taken_ns: int) -> None:
        """Publish a backlog at REPLAY_SPEEDUP times the pace the peer took it from ROS, not all at once.

        A backlog: messages the peer took from ROS more than BACKLOG_NS ago (its buffer after an outage, what queued
        while a new publisher waited for its subscribers). Published in one burst, it would overrun a subscriber's
        KEEP_LAST history before the subscriber took the messages; replayed at twice the original pace it cannot
        overrun a subscriber that kept up with the original publisher, and the backlog still shrinks. Compares the
        peer's clock with this one (Kubernetes nodes keep theirs synchronized); a skew only changes what counts
        as backlog, never what is delivered.
        """
        now = time.monotonic()
        anchor = self._replays.get(topic.name)
        if anchor is None:
            self._replays[topic.name] = (now, taken_ns)
            return
        local_start, taken_start = anchor
        due = local_start + (taken_ns - taken_start) / 1e9 / REPLAY_SPEEDUP
        if due > now:
            await asyncio.sleep(min(due - now, MAX_REPLAY_GAP))
        elif now - due > MAX_REPLAY_GAP:  # far behind (this side was slow): restart the replay from here
            self._replays[topic.name] = (now, taken_ns)

    async def deliver(self, envelope) -> bool:
        """Check one Envelope from the peer and publish it in ROS; False (counted, logged) if it was rejected."""
        topic = self.topics.get(envelope.topic)
        if topic is None:
            self._reject(envelope, "(unknown)", "", "unknown_topic", "the topic is not in the topics file")
            return False
        if topic.outgoing_for(self.role):
            self._reject(
                envelope, topic.name, topic.direction, "wrong_direction", f"the topic goes {topic.direction}, not to here"
            )
            return False
        if envelope.type != topic.type:
            self._reject(
                envelope,
                topic.name,
                topic.direction,
                "type_mismatch",
                f"type {envelope.type[:200]!r}, the topics file says {topic.type}",
            )
            return False
        disabled = getattr(self.ros, "disabled", {}).get(topic.name)
        if disabled:
            self._reject(envelope, topic.name, topic.direction, "topic_disabled", disabled)
            return False
        size = len(envelope.cdr)
        if size > self.settings.max_message_bytes:
            self._reject(
                envelope,
                topic.name,
                topic.direction,
                "oversized",
                f"{size} bytes, more than --max-message-bytes {self.settings.max_message_bytes}",
            )
            return False
        problem = cdr_problem(envelope.cdr)
        if problem:
            self._reject(envelope, topic.name, topic.direction, "bad_cdr", f"not a serialized message: {problem}")
            return False
        last = self._peer_sequences.get(topic.name)
        if last is not None and envelope.sequence > last + 1:
            missing = envelope.sequence - last - 1
            self.metrics.inc("kuberos_bridge_sequence_gaps_total", missing, topic=topic.name, direction=topic.direction)
            self._limited(
                logging.WARNING,
                f"gap {topic.name}",
                "%s: %d messages missing before sequence %d (dropped by the peer or lost in transit)",
                topic.name,
                missing,
                envelope.sequence,
            )
        self._peer_sequences[topic.name] = envelope.sequence
        qos = Qos.from_pb(envelope.qos, topic.depth)
        try:
            publisher = self.ros.publisher(topic, qos)
            if publisher is None:
                publisher = await asyncio.wrap_future(self.ros.create_publisher(topic, qos, size))
                await self._let_subscribers_match(topic, publisher)
            if time.time_ns() - envelope.received_timestamp_ns > BACKLOG_NS:
                await self._replay(topic, envelope.received_timestamp_ns)
            else:
                self._replays.pop(topic.name, None)
            publisher.publish(envelope.cdr)
        except Exception as error:
            self._reject(envelope, topic.name, topic.direction, "publish_failed", describe(error))
            return False
        self.metrics.inc("kuberos_bridge_messages_received_total", topic=topic.name, direction=topic.direction)
        self.metrics.inc("kuberos_bridge_bytes_received_total", size, topic=topic.name, direction=topic.direction)
        return True


# -- server ----------------------------------------------------------------------------------------


class BridgeServer:
    def __init__(self, bridge: Bridge, listen: str, credentials: grpc.ServerCredentials):
        self.bridge, self.listen, self.credentials = bridge, listen, credentials
        self.server: grpc.aio.Server | None = None
        self.port = 0
        self._current: asyncio.Task | None = None

    async def start(self) -> int:
        self.server = grpc.aio.server(options=grpc_options(self.bridge.settings))
        handler = grpc.stream_stream_rpc_method_handler(self._exchange)  # raw bytes: frames are parsed here
        self.server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE, {EXCHANGE: handler}),))
        self.port = self.server.add_secure_port(self.listen, self.credentials)
        if not self.port:
            raise OSError(f"cannot listen on {self.listen}")
        await self.server.start()
        return self.port

    async def stop(self) -> None:
        if self.server is not None:
            await self.server.stop(grace=1.0)

    async def _exchange(self, request_iterator, context):
        bridge = self.bridge
        peer = context.peer()
        names = context.auth_context().get("x509_common_name") or [b"?"]
        who = f"{peer} ({names[0].decode(errors='replace')})"
        try:
            first = await asyncio.wait_for(context.read(), bridge.settings.hello_timeout)
        except TimeoutError:
            log.error("%s sent no Hello within %.0f s; closing", who, bridge.settings.hello_timeout)
            await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, "no Hello")
        if first is grpc.aio.EOF:
            return
        try:
            frame = decode_frame(first)
            if frame.WhichOneof("body") != "hello":
                raise ProtocolError("the first frame must be a Hello")
            if frame.hello.protocol != PROTOCOL:
                raise ProtocolError(f"protocol {frame.hello.protocol}, this server speaks {PROTOCOL}")
        except (FrameError, ProtocolError) as error:
            bridge.metrics.inc("kuberos_bridge_malformed_frames_total")
            log.error("%s: refused: %s", who, error)
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(error))
        previous = self._current
        if previous is not None and not previous.done():
            log.warning("a new connection from %s replaces the session with %s", who, bridge.peer)
            previous.cancel()
            await asyncio.gather(previous, return_exceptions=True)
        self._current = asyncio.current_task()
        await context.write(hello_frame("server", bridge.session, bridge.topics.values(), bridge.settings.max_message_bytes))
        await bridge.run_session(frame.hello, who, context.read, context.write)


def server_credentials(cert: str, key: str, ca: str) -> grpc.ServerCredentials:
    """TLS that requires a client certificate signed by ca."""
    with open(key, "rb") as k, open(cert, "rb") as c, open(ca, "rb") as a:
        return grpc.ssl_server_credentials([(k.read(), c.read())], root_certificates=a.read(), require_client_auth=True)


# -- client ----------------------------------------------------------------------------------------


def tls_probe(target: str, cert: str, key: str, ca: str, server_name: str | None, timeout: float = 5.0) -> str | None:
    """Why a TLS session with the server fails (None if it works), from a handshake of our own.

    With TLS 1.3 a server that refuses the client's certificate says so only after the client finished its
    side of the handshake, and gRPC then reports a closed socket. A handshake with Python's ssl module and the
    same certificate, then a read, gets the server's alert (e.g. "tlsv1 alert unknown ca"), or the end of the
    stream before any HTTP/2 data: gRPC's server closes the connection without an alert.
    """
    import socket
    import ssl

    host, _sep, port = target.rpartition(":")
    host = host.strip("[]")
    context = ssl.create_default_context(cafile=ca)
    context.load_cert_chain(cert, key)
    context.set_alpn_protocols(["h2"])
    try:
        with socket.create_connection((host, int(port)), timeout=timeout) as sock:
            with context.wrap_socket(sock, server_hostname=server_name or host) as tls:
                tls.settimeout(2.0)
                try:
                    first = tls.recv(1)  # a gRPC server's HTTP/2 SETTINGS, or its TLS alert
                except TimeoutError:
                    return None
                if not first:
                    return (
                        "it closed the connection right after the handshake, without HTTP/2 data: it did not accept "
                        "this client's certificate (signed by a CA the server does not trust?)"
                    )
    except ssl.SSLError as error:
        return f"{error.reason or error}".lower().replace("_", " ")
    except OSError:
        return None  # not a TLS problem: the caller reports the connection error as it is
    return None


def channel_credentials(cert: str, key: str, ca: str) -> grpc.ChannelCredentials:
    with open(key, "rb") as k, open(cert, "rb") as c, open(ca, "rb") as a:
        return grpc.ssl_channel_credentials(root_certificates=a.read(), private_key=k.read(), certificate_chain=c.read())


class BridgeClient:
    def __init__(self, bridge: Bridge, target: str, cert: str, key: str, ca: str, server_name: str | None = None):
        self.bridge, self.target, self.server_name = bridge, target, server_name
        self.files = (cert, key, ca)
        self.credentials = channel_credentials(cert, key, ca)
        settings = bridge.settings
        self.backoff = Backoff(initial=settings.backoff_initial, maximum=settings.backoff_max)
        self.attempts = 0

    async def run(self) -> None:
        """Connect, run a session, and reconnect with backoff, until cancelled."""
        bridge = self.bridge
        options = [*grpc_options(bridge.settings), ("grpc.enable_retries", 0)]
        if self.server_name:
            options.append(("grpc.ssl_target_name_override", self.server_name))
        while True:
            self.attempts += 1
            channel = grpc.aio.secure_channel(self.target, self.credentials, options=options)
            established = False
            try:
                call = channel.stream_stream(METHOD)()
                await call.write(hello_frame("client", bridge.session, bridge.topics.values(), bridge.settings.max_message_bytes))
                first = await asyncio.wait_for(call.read(), bridge.settings.hello_timeout)
                if first is grpc.aio.EOF:
                    raise ProtocolError("the server closed the stream without a Hello")
                frame = decode_frame(first)
                if frame.WhichOneof("body") != "hello":
                    raise ProtocolError("the server's first frame is not a Hello")
                established = True
                self.backoff.reset()
                await bridge.run_session(frame.hello, self.target, call.read, call.write)
            except asyncio.CancelledError:
                raise
            except Exception as error:
                if not established:
                    reason = failure_reason(error)
                    if reason == "unavailable" and any(w in describe(error).lower() for w in PROBE_WORDS):
                        refused = await asyncio.to_thread(tls_probe, self.target, *self.files, self.server_name)
                        if refused:
                            reason, error = "tls", ProtocolError(f"the server refused the TLS session: {refused}")
                    bridge.metrics.inc("kuberos_bridge_connect_failures_total", reason=reason)
                    what = "TLS/authentication failure" if reason == "tls" else f"failed ({reason})"
                    text = str(error) if isinstance(error, ProtocolError) else describe(error)
                    bridge._limited(
                        logging.ERROR if reason == "tls" else logging.WARNING, f"connect {reason}",
                        "connection %d to %s: %s: %s", self.attempts, self.target, what, text,
                    )  # fmt: skip
                else:
                    log.warning("session with %s failed: %s", self.target, describe(error))
            finally:
                await channel.close(grace=None)
            delay = self.backoff.next_delay()
            log.debug("reconnecting to %s in %.2f s", self.target, delay)
            await asyncio.sleep(delay)
