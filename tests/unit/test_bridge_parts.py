"""The bridge's parts without ROS: envelopes, the topics file, the drop-oldest buffer, backoff, certificates,
metrics, and the gRPC server and client in this process over loopback with mutual TLS (a stand-in for the ROS
node records what would be published). The ROS 2 side runs for real in tests/integration/test_bridge.py.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import random
import stat
import urllib.request

import grpc
import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import __main__ as cli
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import bridge_pb2 as pb
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import generate_certificates
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.buffer import Backoff, DropOldestBuffer, Outgoing
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.core import (
    METHOD,
    Bridge,
    BridgeClient,
    BridgeServer,
    Settings,
    server_credentials,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.envelope import (
    BEST_EFFORT,
    TRANSIENT_LOCAL,
    FrameError,
    Qos,
    batch_frame,
    cdr_problem,
    decode_frame,
    hello_frame,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.metrics import MetricsServer
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.topics import (
    Topic,
    TopicsError,
    TypeLookupError,
    load_message_type,
    load_topics,
    normalize_type,
)

CDR = b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00"  # std_msgs/String "hi" as Fast DDS serializes it
TOPICS = [
    Topic("/planning/request", "std_msgs/msg/String", "to_client"),
    Topic("/planning/response", "std_msgs/msg/String", "to_server"),
    Topic("/camera/image", "sensor_msgs/msg/Image", "to_client", depth=5),
]
WAIT = 10.0  # every wait in this file is bounded by this many seconds


def item(topic="/planning/request", size=10, sequence=1, type_name="std_msgs/msg/String") -> Outgoing:
    cdr = CDR if size == len(CDR) else b"\x00\x01\x00\x00" + bytes(max(0, size - 4))
    return Outgoing(topic, type_name, cdr, sequence, 11, 22, Qos())


# --- envelopes --------------------------------------------------------------------------------------------


def test_a_batch_frame_round_trips_every_envelope_field():
    qos = Qos(BEST_EFFORT, TRANSIENT_LOCAL, 7)
    items = [Outgoing("/a", "std_msgs/msg/String", CDR, 5, 123, 456, qos), item("/b", 2000, 9)]
    frame = decode_frame(batch_frame(items, now_ns=789))
    assert frame.WhichOneof("body") == "batch"
    first, second = frame.batch.envelopes
    assert (first.topic, first.type, first.cdr, first.sequence) == ("/a", "std_msgs/msg/String", CDR, 5)
    assert (first.source_timestamp_ns, first.received_timestamp_ns, first.sent_timestamp_ns) == (123, 456, 789)
    assert Qos.from_pb(first.qos, 10) == qos
    assert (second.topic, len(second.cdr), second.sequence) == ("/b", 2000, 9)


def test_hello_carries_role_session_topics_and_limit():
    frame = decode_frame(hello_frame("client", "abc", TOPICS, 1234))
    hello = frame.hello
    assert (hello.role, hello.session, hello.protocol, hello.max_message_bytes) == ("client", "abc", 1, 1234)
    assert [(t.name, t.type, t.direction) for t in hello.topics] == [(t.name, t.type, t.direction) for t in TOPICS]


def test_an_unspecified_qos_falls_back_to_reliable_volatile_and_the_topic_depth():
    assert Qos.from_pb(pb.Qos(), 4) == Qos("reliable", "volatile", 4)


@pytest.mark.parametrize(
    "data, words",
    [
        (b"\xff\xfe\xfd\xfc garbage", "do not parse"),
        (b"", "neither hello nor batch"),
        (pb.TopicInfo(direction="x").SerializeToString(), "neither hello nor batch"),  # parses: an unknown field 3
    ],
)
def test_malformed_frames_raise_frame_error(data, words):
    with pytest.raises(FrameError, match=words):
        decode_frame(data)


def test_random_bytes_never_raise_anything_but_frame_error():
    rng = random.Random(7)
    for _ in range(2000):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(64)))
        with contextlib.suppress(FrameError):
            decode_frame(data)


def test_cdr_header_check():
    assert cdr_problem(CDR) is None
    assert "shorter" in cdr_problem(b"\x00\x01")
    assert "representation" in cdr_problem(b"\x12\x34\x00\x00abcd")


# --- the topics file --------------------------------------------------------------------------------------


def write(tmp_path, text: str) -> str:
    path = tmp_path / "topics.yml"
    path.write_text(text, encoding="utf-8")
    return str(path)


def test_the_documented_topics_file_loads(tmp_path):
    path = write(
        tmp_path,
        "topics:\n"
        "- {name: /planning/request, type: std_msgs/msg/String, direction: to_client}\n"
        "- {name: /planning/response, type: std_msgs/String, direction: to_server, depth: 3}\n",
    )
    topics = load_topics(path)
    assert topics == [
        Topic("/planning/request", "std_msgs/msg/String", "to_client", 10),
        Topic("/planning/response", "std_msgs/msg/String", "to_server", 3),
    ]
    assert topics[0].outgoing_for("server") and not topics[0].outgoing_for("client")
    assert topics[1].outgoing_for("client") and not topics[1].outgoing_for("server")


def test_every_problem_is_reported_with_the_file_and_field(tmp_path):
    path = write(
        tmp_path,
        "topics:\n"
        "- {name: planning, type: std_msgs/msg/String, direction: to_client}\n"
        "- {name: /a, type: 'not a type', direction: sideways, depth: 0, colour: red}\n"
        "- {name: /b}\n"
        "- {name: /b, type: std_msgs/msg/String, direction: to_server}\n"
        "- just a string\n"
        "extra: 1\n",
    )
    with pytest.raises(TopicsError) as caught:
        load_topics(path)
    text = str(caught.value)
    for expected in (
        f"{path}: extra: unknown key",
        f"{path}: topics[0].name: 'planning' is not an absolute ROS 2 topic name",
        f"{path}: topics[1].type: 'not a type' is not a message type name",
        f"{path}: topics[1].direction: 'sideways' is neither to_client nor to_server",
        f"{path}: topics[1].depth: 0 is not a whole number",
        f"{path}: topics[1].colour: unknown field",
        f"{path}: topics[2].type: missing",
        f"{path}: topics[2].direction: missing",
        f"{path}: topics[3].name: /b is already topics[2]",
        f"{path}: topics[4]: must be a mapping",
    ):
        assert expected in text, text
    assert len(caught.value.problems) == 10


@pytest.mark.parametrize(
    "text, words",
    [
        ("", "must be a mapping"),
        ("topics: []\n", "topics: must be a non-empty list"),
        ("topics: [\n", "not valid YAML"),
        ("- a\n", "must be a mapping"),
    ],
)
def test_unusable_topics_files(tmp_path, text, words):
    with pytest.raises(TopicsError, match=words):
        load_topics(write(tmp_path, text))


def test_a_missing_topics_file_names_the_file(tmp_path):
    missing = str(tmp_path / "nope.yml")
    with pytest.raises(TopicsError, match=f"{missing}: cannot read"):
        load_topics(missing)


def test_type_names_normalize():
    assert normalize_type("std_msgs/String") == "std_msgs/msg/String"
    assert normalize_type("sensor_msgs/msg/Image") == "sensor_msgs/msg/Image"
    for bad in ("String", "std_msgs/srv/Empty", "a/b/c/d", "std_msgs/msg/", 3, None):
        with pytest.raises(TypeLookupError):
            normalize_type(bad)


@pytest.mark.ros
def test_type_lookup_imports_the_message_class_or_says_why_not():
    from std_msgs.msg import String

    assert load_message_type("std_msgs/msg/String") is String
    assert load_message_type("sensor_msgs/Image").__name__ == "Image"
    with pytest.raises(TypeLookupError, match=r"std_msgs\.msg has no message Strin \(did you mean String"):
        load_message_type("std_msgs/msg/Strin")
    with pytest.raises(TypeLookupError, match=r"kuberos_no_such_pkg\.msg cannot be imported.*is the ROS 2 package"):
        load_message_type("kuberos_no_such_pkg/msg/Thing")


def test_cli_reports_a_bad_topics_file_and_exits_2(tmp_path, capsys):
    path = write(tmp_path, "topics:\n- {name: /a, type: std_msgs/msg/String, direction: up}\n")
    argv = ["server", "--listen", "127.0.0.1:0", "--cert", "c", "--key", "k", "--ca", "a", "--topics", path]
    assert cli.main(argv) == 2
    assert f"{path}: topics[0].direction: 'up' is neither to_client nor to_server" in capsys.readouterr().err


# --- buffer and backoff -----------------------------------------------------------------------------------


def test_the_buffer_drops_the_oldest_and_counts_per_topic():
    buffer = DropOldestBuffer(max_messages=3, max_bytes=10**6)
    for n in range(1, 6):
        buffer.push(item("/a" if n % 2 else "/b", sequence=n))
    assert [i.sequence for i in buffer.pop_batch(10, 10**6)] == [3, 4, 5]
    assert buffer.dropped == {"/a": 1, "/b": 1}
    assert buffer.take_report() == {"/a": 1, "/b": 1} and buffer.take_report() == {}


def test_the_buffer_bounds_bytes_too_and_a_message_larger_than_it_is_dropped():
    buffer = DropOldestBuffer(max_messages=100, max_bytes=2500)
    for n in range(1, 4):
        buffer.push(item(size=1000, sequence=n))
    assert len(buffer) == 2 and buffer.bytes == 2000 and buffer.dropped == {"/planning/request": 1}
    assert buffer.push(item("/big", size=5000)) == 3  # the two waiting ones, then itself
    assert len(buffer) == 0 and buffer.bytes == 0


def test_batches_respect_count_and_bytes_but_always_take_one():
    buffer = DropOldestBuffer(max_messages=100, max_bytes=10**7)
    for n in range(1, 11):
        buffer.push(item(size=1000, sequence=n))
    assert [i.sequence for i in buffer.pop_batch(3, 10**6)] == [1, 2, 3]
    assert [i.sequence for i in buffer.pop_batch(100, 2500)] == [4, 5]
    assert [i.sequence for i in buffer.pop_batch(100, 10)] == [6]
    batch = buffer.pop_batch(100, 10**6)
    assert [i.sequence for i in batch] == [7, 8, 9, 10]
    assert buffer.requeue(batch) == 0 and [i.sequence for i in buffer.pop_batch(2, 10**6)] == [7, 8]


def test_requeue_keeps_order_and_limits():
    buffer = DropOldestBuffer(max_messages=3, max_bytes=10**6)
    buffer.push(item(sequence=1))
    batch = buffer.pop_batch(10, 10**6)
    for n in (2, 3, 4):
        buffer.push(item(sequence=n))
    assert buffer.requeue(batch) == 1  # 1, 2, 3, 4 is one too many: the oldest (1) goes
    assert [i.sequence for i in buffer.pop_batch(10, 10**6)] == [2, 3, 4]


def test_a_waiting_consumer_is_woken_once_by_the_next_push():
    buffer = DropOldestBuffer(10, 10**6)
    wakes = []
    buffer.waker = lambda: wakes.append(1)
    buffer.push(item())
    assert wakes == []  # nobody was waiting
    assert buffer.pop_batch(10, 10**6) and buffer.pop_batch(10, 10**6) == []
    buffer.push(item())
    buffer.push(item())
    assert wakes == [1]


def test_backoff_doubles_up_to_the_maximum_with_bounded_jitter_and_resets():
    backoff = Backoff(initial=0.1, maximum=1.0, factor=2.0, jitter=0.2, rng=random.Random(1))
    delays = [backoff.next_delay() for _ in range(8)]
    for delay, base in zip(delays, [0.1, 0.2, 0.4, 0.8, 1.0, 1.0, 1.0, 1.0], strict=True):
        assert base * 0.8 <= delay <= base * 1.2
    backoff.reset()
    assert backoff.next_delay() <= 0.12
    with pytest.raises(ValueError):
        Backoff(initial=0)


# --- certificates -----------------------------------------------------------------------------------------


def test_certificates_chain_to_one_ca_with_the_right_names_and_usages(tmp_path):
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    paths = generate_certificates(str(tmp_path / "certs"), "bridge.kuberos.svc", extra_server_names=["10.0.0.5"])
    assert set(paths) == {"ca_cert", "ca_key", "server_cert", "server_key", "client_cert", "client_key"}
    assert {os.path.basename(p) for p in paths.values()} == {
        "ca.crt", "ca.key", "server.crt", "server.key", "client.crt", "client.key",
    }  # fmt: skip
    for name in ("ca_key", "server_key", "client_key"):
        assert stat.S_IMODE(os.stat(paths[name]).st_mode) == 0o600

    def load(name):
        with open(paths[name], "rb") as handle:
            return x509.load_pem_x509_certificate(handle.read())

    ca, server, client = load("ca_cert"), load("server_cert"), load("client_cert")
    for leaf in (server, client):
        leaf.verify_directly_issued_by(ca)
    sans = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sans.get_values_for_type(x509.DNSName) == ["bridge.kuberos.svc"]
    assert [str(a) for a in sans.get_values_for_type(x509.IPAddress)] == ["10.0.0.5"]
    usage = server.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert list(usage) == [ExtendedKeyUsageOID.SERVER_AUTH]
    usage = client.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert list(usage) == [ExtendedKeyUsageOID.CLIENT_AUTH]
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca


def test_certs_command_writes_the_files_and_prints_their_paths(tmp_path, capsys):
    assert cli.main(["certs", "--out", str(tmp_path), "--server-name", "127.0.0.1"]) == 0
    out = capsys.readouterr().out
    assert '"server_cert"' in out and os.path.exists(tmp_path / "server.crt")
    with pytest.raises(ValueError):
        generate_certificates(str(tmp_path), " ")


# --- metrics ----------------------------------------------------------------------------------------------


def test_metrics_render_prometheus_text_and_serve_health(tmp_path):
    bridge = Bridge("server", TOPICS, Settings(buffer_messages=2))
    bridge.metrics.inc("kuberos_bridge_messages_sent_total", 3, topic="/planning/request", direction="to_client")
    for n in range(5):
        bridge.take(TOPICS[0], Qos(), CDR)
        assert bridge._sequences["/planning/request"] == n + 1
    text = bridge.metrics.render()
    assert 'kuberos_bridge_messages_sent_total{direction="to_client",topic="/planning/request"} 3' in text
    assert 'kuberos_bridge_dropped_messages_total{direction="to_client",reason="buffer_full",topic="/planning/request"} 3' in text
    assert "kuberos_bridge_buffered_messages 2" in text and "# TYPE kuberos_bridge_connected gauge" in text
    loop = asyncio.new_event_loop()
    bridge.bind(loop)
    server = MetricsServer(bridge, "127.0.0.1", 0)
    server.start()
    try:
        base = f"http://127.0.0.1:{server.port}"
        with urllib.request.urlopen(f"{base}/metrics", timeout=WAIT) as response:
            assert b"kuberos_bridge_buffered_messages 2" in response.read()
        with urllib.request.urlopen(f"{base}/healthz", timeout=WAIT) as response:
            assert response.status == 200
        with pytest.raises(urllib.error.HTTPError) as caught:
            urllib.request.urlopen(f"{base}/readyz", timeout=WAIT)
        assert caught.value.code == 503
    finally:
        server.stop()
        loop.close()


def test_an_oversized_message_from_ros_is_dropped_and_counted(caplog):
    bridge = Bridge("server", TOPICS, Settings(max_message_bytes=100))
    with caplog.at_level(logging.ERROR):
        bridge.take(TOPICS[0], Qos(), CDR + bytes(200))
    assert len(bridge.buffer) == 0
    assert (
        bridge.metrics.get(
            "kuberos_bridge_dropped_messages_total", topic="/planning/request", direction="to_client", reason="oversized"
        )
        == 1
    )
    assert "larger than the limit of 100 bytes" in caplog.text


# --- server and client over loopback with mutual TLS ------------------------------------------------------


class FakePublisher:
    def __init__(self, log, topic, qos):
        self.log, self.topic, self.qos = log, topic, qos

    def publish(self, cdr):
        self.log.append((self.topic, self.qos, cdr))


class FakeRos:
    """What Bridge needs of RosSide: publishers of incoming topics (recorded) and disabled topics."""

    def __init__(self, disabled=None):
        self.published, self.publishers, self.disabled = [], {}, disabled or {}

    def alive(self):
        return True

    def publisher(self, topic, qos):
        return self.publishers.get((topic.name, qos))

    def create_publisher(self, topic, qos, message_bytes=0):
        future = concurrent.futures.Future()
        self.publishers[(topic.name, qos)] = FakePublisher(self.published, topic.name, qos)
        future.set_result(self.publishers[(topic.name, qos)])
        return future


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    base = tmp_path_factory.mktemp("bridge-certs")
    return generate_certificates(str(base / "good"), "localhost"), generate_certificates(str(base / "other"), "localhost")


async def until(condition, what: str, timeout: float = WAIT) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not condition():
        if loop.time() > deadline:
            raise AssertionError(f"{what}: not within {timeout} s")
        await asyncio.sleep(0.02)


def make_bridge(role, loop, settings=None, disabled=None) -> Bridge:
    bridge = Bridge(role, TOPICS, settings or Settings(backoff_initial=0.05, backoff_max=0.2))
    bridge.bind(loop)
    bridge.ros = FakeRos(disabled)
    return bridge


async def start_server(bridge, good, port=0) -> BridgeServer:
    server = BridgeServer(
        bridge, f"127.0.0.1:{port}", server_credentials(good["server_cert"], good["server_key"], good["ca_cert"])
    )
    await server.start()
    return server


def start_client(bridge, port, files) -> tuple[BridgeClient, asyncio.Task]:
    client = BridgeClient(bridge, f"127.0.0.1:{port}", files["client_cert"], files["client_key"], files["ca_cert"], "localhost")
    return client, asyncio.create_task(client.run())


async def stop(task):
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


def test_messages_cross_both_ways_with_their_qos(certs):
    good, _ = certs

    async def scenario():
        loop = asyncio.get_running_loop()
        server_bridge, client_bridge = make_bridge("server", loop), make_bridge("client", loop)
        server = await start_server(server_bridge, good)
        _, task = start_client(client_bridge, server.port, good)
        try:
            await until(lambda: server_bridge.connected and client_bridge.connected, "session")
            qos = Qos(BEST_EFFORT, TRANSIENT_LOCAL, 5)
            server_bridge.take(TOPICS[2], qos, CDR + bytes(2_000_000))  # 2 MB image, to_client
            server_bridge.take(TOPICS[0], Qos(), CDR)
            client_bridge.take(TOPICS[1], Qos(), CDR)  # to_server
            await until(lambda: len(client_bridge.ros.published) == 2, "to the client")
            await until(lambda: len(server_bridge.ros.published) == 1, "to the server")
            image = client_bridge.ros.published[0]
            assert image[0] == "/camera/image" and image[1] == qos and len(image[2]) == len(CDR) + 2_000_000
            assert server_bridge.ros.published == [("/planning/response", Qos(), CDR)]
            m = client_bridge.metrics
            assert m.get("kuberos_bridge_messages_received_total", topic="/camera/image", direction="to_client") == 1
            assert m.get("kuberos_bridge_bytes_received_total", topic="/camera/image", direction="to_client") == 2_000_011
            assert server_bridge.metrics.get("kuberos_bridge_messages_sent_total") == 2
        finally:
            await stop(task)
            await server.stop()

    asyncio.run(asyncio.wait_for(scenario(), 60))


def test_bad_input_from_the_peer_is_counted_and_never_ends_the_server(certs, caplog):
    good, _ = certs

    async def scenario():
        loop = asyncio.get_running_loop()
        bridge = make_bridge("server", loop, Settings(max_message_bytes=1000), disabled={"/camera/image": "no sensor_msgs"})
        server = await start_server(bridge, good)
        credentials = grpc.ssl_channel_credentials(
            open(good["ca_cert"], "rb").read(), open(good["client_key"], "rb").read(), open(good["client_cert"], "rb").read()
        )
        options = [("grpc.ssl_target_name_override", "localhost")]
        try:
            async with grpc.aio.secure_channel(f"127.0.0.1:{server.port}", credentials, options=options) as channel:
                # 1. garbage instead of a Hello: refused with INVALID_ARGUMENT
                call = channel.stream_stream(METHOD)()
                await call.write(b"\xff\x00garbage")
                with pytest.raises(grpc.aio.AioRpcError) as caught:
                    await asyncio.wait_for(call.read(), WAIT)
                assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
                # 2. a proper Hello, then every kind of bad frame and envelope, then a good one
                call = channel.stream_stream(METHOD)()
                await call.write(hello_frame("client", "s1", TOPICS, 1000))
                assert decode_frame(await asyncio.wait_for(call.read(), WAIT)).hello.role == "server"
                await call.write(b"\x0a\x05broken")
                await call.write(b"")
                await call.write(hello_frame("client", "s1", TOPICS, 1000))

                def envelope(topic="/planning/response", type_name="std_msgs/msg/String", cdr=CDR, sequence=1):
                    return Outgoing(topic, type_name, cdr, sequence, 0, 0, Qos())

                await call.write(
                    batch_frame(
                        [
                            envelope(topic="/not/configured"),
                            envelope(topic="/planning/request"),  # goes to_client: the client must not send it
                            envelope(type_name="std_msgs/msg/Int32"),
                            envelope(type_name="no_such_pkg/msg/Nope"),
                            envelope(cdr=CDR + bytes(2000)),
                            envelope(cdr=b"\x7f\x7f\x00\x00data"),
                            envelope(topic="/camera/image", type_name="sensor_msgs/msg/Image"),
                            envelope(sequence=1),
                            envelope(sequence=5),  # 2, 3 and 4 never came
                        ]
                    )
                )
                await until(lambda: len(bridge.ros.published) == 2, "the good envelopes published")
                await call.done_writing()
        finally:
            await server.stop()
        m = bridge.metrics
        assert m.get("kuberos_bridge_malformed_frames_total") == 4  # garbage first frame, broken, empty, second Hello
        rejected = {
            reason: m.get("kuberos_bridge_rejected_messages_total", topic=topic, direction=direction, reason=reason)
            for topic, direction, reason in [
                ("(unknown)", "", "unknown_topic"),
                ("/planning/request", "to_client", "wrong_direction"),
                ("/planning/response", "to_server", "type_mismatch"),
                ("/planning/response", "to_server", "oversized"),
                ("/planning/response", "to_server", "bad_cdr"),
                ("/camera/image", "to_client", "topic_disabled"),
            ]
        }
        assert rejected == {
            "unknown_topic": 1, "wrong_direction": 1, "type_mismatch": 2, "oversized": 1, "bad_cdr": 1, "topic_disabled": 0,
        }  # fmt: skip
        # /camera/image goes to_client, so a client sending it is refused before its disabled state matters
        assert (
            m.get(
                "kuberos_bridge_rejected_messages_total", topic="/camera/image", direction="to_client", reason="wrong_direction"
            )
            == 1
        )
        assert m.get("kuberos_bridge_sequence_gaps_total", topic="/planning/response", direction="to_server") == 3
        assert m.get("kuberos_bridge_messages_received_total") == 2

    with caplog.at_level(logging.WARNING):
        asyncio.run(asyncio.wait_for(scenario(), 60))
    assert "refused: " in caplog.text and "malformed frame" in caplog.text and "not published: type" in caplog.text


def test_a_client_with_a_certificate_from_another_ca_is_refused(certs, caplog):
    good, other = certs
    foreign = {**other, "ca_cert": good["ca_cert"]}  # trusts the right server, but its own certificate is foreign

    async def scenario():
        loop = asyncio.get_running_loop()
        server_bridge, client_bridge = make_bridge("server", loop), make_bridge("client", loop)
        server = await start_server(server_bridge, good)
        _, task = start_client(client_bridge, server.port, foreign)
        try:
            await until(lambda: client_bridge.metrics.get("kuberos_bridge_connect_failures_total", reason="tls") >= 2, "refusals")
            client_bridge.take(TOPICS[1], Qos(), CDR)
            await asyncio.sleep(0.3)
        finally:
            await stop(task)
            await server.stop()
        assert server_bridge.metrics.get("kuberos_bridge_connections_total") == 0
        assert client_bridge.metrics.get("kuberos_bridge_connections_total") == 0
        assert server_bridge.ros.published == [] and len(client_bridge.buffer) == 1

    with caplog.at_level(logging.ERROR):
        asyncio.run(asyncio.wait_for(scenario(), 60))
    assert "TLS/authentication failure" in caplog.text and "certificate" in caplog.text


def test_the_client_reconnects_and_reports_what_it_dropped_while_the_server_was_away(certs, caplog):
    good, _ = certs

    async def scenario():
        loop = asyncio.get_running_loop()
        server_bridge = make_bridge("server", loop)
        client_bridge = make_bridge("client", loop, Settings(buffer_messages=5, backoff_initial=0.05, backoff_max=0.2))
        server = await start_server(server_bridge, good)
        port = server.port
        _, task = start_client(client_bridge, port, good)
        try:
            await until(lambda: client_bridge.connected, "first session")
            client_bridge.take(TOPICS[1], Qos(), CDR)
            await until(lambda: len(server_bridge.ros.published) == 1, "first message")
            await server.stop()
            await until(lambda: not client_bridge.connected, "the client notices")
            for _ in range(12):  # 5 stay buffered, 7 are dropped
                client_bridge.take(TOPICS[1], Qos(), CDR)
            await asyncio.sleep(0.5)  # a few reconnection attempts fail meanwhile
            server = await start_server(server_bridge, good, port)
            await until(lambda: len(server_bridge.ros.published) == 6, "the buffered messages after the restart")
        finally:
            await stop(task)
            await server.stop()
        m = client_bridge.metrics
        assert (
            m.get(
                "kuberos_bridge_dropped_messages_total", topic="/planning/response", direction="to_server", reason="buffer_full"
            )
            == 7
        )
        assert m.get("kuberos_bridge_reconnects_total") == 1 and m.get("kuberos_bridge_connect_failures_total") >= 1
        assert (
            server_bridge.metrics.get("kuberos_bridge_sequence_gaps_total", topic="/planning/response", direction="to_server")
            == 7
        )

    with caplog.at_level(logging.INFO):
        asyncio.run(asyncio.wait_for(scenario(), 60))
    assert "send buffer full" in caplog.text
    assert "/planning/response 7 dropped while disconnected; 5 buffered messages to send" in caplog.text
