"""A module's output without kubectl: the instance that serves a robot, Secrets kept out, several containers
labelled (plugins/module_utils/kuberos/module_logs.py and kuberos_deploy/module_log_reader.py, without a cluster)."""

from __future__ import annotations

import base64
import json
import textwrap
import time
from urllib.parse import quote, quote_plus

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.module_logs import (
    Redactor,
    instance_for,
    labelled,
    redact,
    robots_of,
    secret_refs,
    secret_values,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.module_log_reader import (
    LogNotFound,
    read_module_log,
)


def _deployment(name, module, robot="", robots="", namespace="kuberos-test-fleet"):
    labels = {"kuberos.io/deployment": "pnp", "kuberos.io/module": module, "kuberos.io/component": "ros-module"}
    if robot:
        labels["robot.kuberos.io/name"] = robot
    return {
        "kind": "Deployment",
        "metadata": {
            "name": name,
            "namespace": namespace,
            "labels": labels,
            "annotations": {"kuberos.io/robots": robots or robot},
        },
    }


DEPLOYMENTS = [
    _deployment("pnp-planner-fetch-1", "planner", "fetch-1"),
    _deployment("pnp-planner-fetch-2", "planner", "fetch-2"),
    _deployment("pnp-coordinator-shared-0", "coordinator", robots="fetch-1,fetch-2"),
]


def test_the_instance_serving_a_robot_is_its_dedicated_one_or_the_shared_one_listing_it():
    assert instance_for(DEPLOYMENTS, "pnp", "planner", "fetch-2")["metadata"]["name"] == "pnp-planner-fetch-2"
    assert instance_for(DEPLOYMENTS, "pnp", "coordinator", "fetch-2")["metadata"]["name"] == "pnp-coordinator-shared-0"
    assert instance_for(DEPLOYMENTS, "pnp", "planner", "fetch-3") is None
    assert instance_for(DEPLOYMENTS, "other", "planner", "fetch-1") is None
    assert robots_of(DEPLOYMENTS, "pnp", "planner") == ["fetch-1", "fetch-2"]


def test_secrets_a_pod_can_read_are_found_and_their_values_never_show():
    spec = {
        "containers": [
            {
                "env": [{"name": "TOKEN", "valueFrom": {"secretKeyRef": {"name": "api", "key": "token"}}}],
                "envFrom": [{"secretRef": {"name": "all-of-it"}}],
            }
        ],
        "volumes": [
            {"name": "tls", "secret": {"secretName": "bridge-tls"}},
            {"name": "p", "projected": {"sources": [{"secret": {"name": "projected"}}]}},
        ],
    }
    assert secret_refs(spec) == [("all-of-it", ""), ("api", "token"), ("bridge-tls", ""), ("projected", "")]
    secret = {"metadata": {"name": "api"}, "data": {"token": base64.b64encode(b"s3cr3t-value").decode(), "other": "eA=="}}
    assert secret_values(secret, "token") == {"api/token": "s3cr3t-value"}
    text = (
        "connecting with s3cr3t-value\nkey:\n-----BEGIN PRIVATE KEY-----\nMIIEv\nabc\n-----END PRIVATE KEY-----\n"
        "Authorization: Bearer abcdefgh12345678\n"
        "jwt eyJhbGciOiJSUzI1NiJ9.eyJzdWIiOiJzeXN0ZW0.c2lnbmF0dXJlc2ln end\nok"
    )
    shown = redact(text, {"api/token": "s3cr3t-value", "short/x": "ab"})
    assert "s3cr3t-value" not in shown and "[redacted: api/token]" in shown
    assert "MIIEv" not in shown and "[redacted: private key]" in shown
    assert "abcdefgh12345678" not in shown and "eyJhbGci" not in shown and shown.endswith("end\nok")
    multi = redact("line one of the cert\nsecond line here", {"tls/cert": "line one of the cert\nsecond line here"})
    assert "line one" not in multi and "second line" not in multi


KEY_BODY = textwrap.wrap(base64.b64encode(bytes(range(256)) * 3).decode(), 64)
KEY = ["-----BEGIN RSA PRIVATE KEY-----", *KEY_BODY, "-----END RSA PRIVATE KEY-----"]
LOG = ["[INFO] [1.5] [planner]: starting", *KEY, "[INFO] [2.5] [planner]: ready"]


def _shows_key(text):
    return [line for line in KEY_BODY if line in text]


def test_a_key_body_is_redacted_whatever_the_window_shows_of_it():
    for start in range(len(LOG)):  # the dashboard's tail and lines=N start anywhere, inside the key too
        for end in range(start + 1, len(LOG) + 1):
            shown = redact("\n".join(LOG[start:end]), {})
            assert _shows_key(shown) == [], (start, end)
    assert redact("\n".join(LOG[3:]), {}).split("\n") == ["[redacted: private key]", "[INFO] [2.5] [planner]: ready"]
    assert redact("\n".join(LOG), {}).split("\n") == [LOG[0], "[redacted: private key]", LOG[-1]]


def test_a_key_split_across_follow_polls_shows_no_part_of_it():
    short = ["-----BEGIN PGP PRIVATE KEY BLOCK-----", "", "lQOYBF", "x9Kq", "=ab12", "-----END PGP PRIVATE KEY BLOCK-----"]
    for cut in range(1, len(short)):
        redactor = Redactor({})
        polls = [redactor.redact("\n".join(["first", *short[:cut]])), redactor.redact("\n".join([*short[cut:], "after"]))]
        assert not any(piece in "\n".join(polls) for piece in ("lQOYBF", "x9Kq", "ab12")), cut
        assert polls[0].startswith("first\n[redacted: PGP private key]") and polls[1].endswith("after")


def test_lines_of_a_multi_line_secret_value_are_redacted_alone():
    value = "user = fleet-admin-7\nkey = 0a9f8e7d6c5b4a39\n"
    shown = redact("loaded config\nkey = 0a9f8e7d6c5b4a39\nnext", {"cfg/ini": value})
    assert shown == "loaded config\n[redacted: cfg/ini]\nnext"


ENCODINGS = "raw base64 base64-nopad urlsafe urlsafe-nopad base64-newline percent form json json-utf8 hex HEX".split()


@pytest.mark.parametrize(
    "encode",
    [
        lambda v: v,
        lambda v: base64.b64encode(v.encode()).decode(),
        lambda v: base64.b64encode(v.encode()).decode().rstrip("="),
        lambda v: base64.urlsafe_b64encode(v.encode()).decode(),
        lambda v: base64.urlsafe_b64encode(v.encode()).decode().rstrip("="),
        lambda v: base64.b64encode(v.encode() + b"\n").decode(),
        lambda v: quote(v, safe=""),
        lambda v: quote_plus(v),
        lambda v: json.dumps(v)[1:-1],
        lambda v: json.dumps(v, ensure_ascii=False)[1:-1],
        lambda v: v.encode().hex(),
        lambda v: v.encode().hex().upper(),
    ],
    ids=ENCODINGS,
)
def test_a_secret_value_is_redacted_in_its_encodings(encode):
    value = 'p@ss "wörd"/+?&=\\ with\nsecond line ~~>>'
    shown = redact(f"cfg {encode(value)} end", {"db/password": value})
    assert shown == ("cfg [redacted: db/password]\n" if "\n" in encode(value) else "cfg ") + "[redacted: db/password] end"
    assert redact(f"cfg {encode('abc')} end", {"short/x": "abc"}) == f"cfg {encode('abc')} end", "shorter than MIN_SECRET"


def test_a_secret_value_inside_a_larger_base64_text_is_redacted():
    """``Authorization: Basic base64(user:value)`` and a base64 config file holding the value, at any offset."""
    value = "hunter2-correct-horse-battery"
    for prefix in ("", "a", "ab", "user:", '{"password": "'):
        encoded = base64.b64encode(f"{prefix}{value}\n".encode()).decode()
        shown = redact(f"sent {encoded}", {"db/password": value})
        # what shows: the groups of the prefix, and the two groups the value shares with its neighbours
        assert shown.count("[redacted: db/password]") == 1
        assert len(shown.replace("[redacted: db/password]", "")) <= len("sent ") + 4 * (len(prefix) // 3) + 12


@pytest.mark.parametrize(
    ("line", "shown"),
    [
        ("> Authorization: Basic cm9ib3Q6aHVudGVyMg==", "> Authorization: Basic [redacted: credentials]"),
        ("{'authorization': 'basic cm9ib3Q6aHVudGVyMg=='}", "{'authorization': 'basic [redacted: credentials]'}"),
        ("retrying with Basic cm9ib3Q6aHVudGVyMg==", "retrying with Basic [redacted: credentials]"),
        ("Authorization: Bearer abcdefgh12345678", "Authorization: Bearer [redacted: token]"),
        ("Proxy-Authorization: Zm9vOmJhcg", "Proxy-Authorization: [redacted: credentials]"),
        ("postgres://planner:s3cr%40t@db.fleet.svc:5432/maps", "postgres://planner:[redacted: password]@db.fleet.svc:5432/maps"),
        ("clone https://bot:gh-p4ss@git.example.com/r.git", "clone https://bot:[redacted: password]@git.example.com/r.git"),
        ("redis://:p4ss;w0rd@cache:6379/0", "redis://:[redacted: password]@cache:6379/0"),
        ("using access key AKIAIOSFODNN7EXAMPLE", "using access key [redacted: AWS access key id]"),
        ("aws_secret_access_key = wJalrXUtnFEMI/K7MDENG/bPxRfiCYEXAMPLEKEY", "aws_secret_access_key = [redacted: key]"),
        ("AWS_SESSION_TOKEN=IQoJb3JpZ2luX2VjEJr", "AWS_SESSION_TOKEN=[redacted: token]"),
        (
            '{"AccessKeyId": "ASIAY34FZKBOKMUTVV7A", "SecretAccessKey": "wJalrXUtnFEMI/K7MDENG"}',
            '{"AccessKeyId": "[redacted: AWS access key id]", "SecretAccessKey": "[redacted: key]"}',
        ),
        (
            "AccountName=robots;AccountKey=Eby8vdM02xNOcqFlqUwJPLlmEtlCDXJ1OUzFT50uSRZ6IFsu==;EndpointSuffix=core",
            "AccountName=robots;AccountKey=[redacted: key];EndpointSuffix=core",
        ),
        (
            '{"private_key": "-----BEGIN PRIVATE KEY-----\\nMIIEvQIBADANBg\\n-----END PRIVATE KEY-----\\n", "x": 1}',
            '{"private_key": "[redacted: private key]\\n", "x": 1}',
        ),
        ("X-Api-Key: 5f0c2a9e81d3", "X-Api-Key: [redacted: key]"),
        ("x-auth-token: abc123", "x-auth-token: [redacted: token]"),
        ('{"apiKey": "abc123"}', '{"apiKey": "[redacted: key]"}'),
        ("token: abc123", "token: [redacted: token]"),
        ("refresh_token=abc123&z=1", "refresh_token=[redacted: token]&z=1"),
        ("password=hunter2 next", "password=[redacted: password] next"),
        ("{'password': 'hunter 2'}", "{'password': '[redacted: password]'}"),
        ("client_secret=abc123", "client_secret=[redacted: secret]"),
        ("--token=abc123", "--token=[redacted: token]"),
        ("GET /blob?sv=2022&sig=AbC%2Fd3&se=1", "GET /blob?sv=2022&sig=[redacted: signature]&se=1"),
        ("signing with ghp_abcdefghijklmnopqrstuvwxyz0123456789", "signing with [redacted: token]"),
        ("jwt eyJhbGciOiJSUzI1NiJ9.eyJzdWIiOiJzeXN0ZW0.c2lnbmF0dXJlc2ln end", "jwt [redacted: token] end"),
    ],
)
def test_credentials_are_redacted_and_their_names_kept(line, shown):
    assert redact(line, {}) == shown


@pytest.mark.parametrize(
    "line",
    [
        "[INFO] [1732788001.123456789] [motion_planner]: Planning request received for group 'arm'",
        "[WARN] [1732788001.5] [controller_manager]: Overrun: 2.3 ms over the 10 ms period",
        "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08",
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855 /opt/ros/humble/setup.bash",
        "/opt/ros/humble/share/robotdescription/urdf/robotwithgripperandcamera",
        "/home/robot/workspace/install/PickAndPlace/share/PickAndPlace/launch/Bringup2",
        "/opt/ros/Humble/share/MoveIt2/config/RobotArm3/URDF",
        "2b1d6a0e-6f1c-4a51-9c58-1f1e2d3c4b5a",
        "ghcr.io/kuberos/motion-planner:1.4.2@sha256:e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
        "http://10.42.0.17:8080/healthz and https://registry.local:5000/v2/",
        "-----BEGIN CERTIFICATE-----",
        "tokens per second: 1200; keys: left, right; Password accepted",
        "basic navigation started",
        "TransformListenerImplNodeInterfaceWrapperFactory",
        "done",
    ],
)
def test_ordinary_log_lines_survive(line):
    assert redact(f"[INFO] start\n{line}\n[INFO] end", {}) == f"[INFO] start\n{line}\n[INFO] end"


def test_a_certificate_is_shown_a_private_key_is_not():
    cert = ["-----BEGIN CERTIFICATE-----", *KEY_BODY, "-----END CERTIFICATE-----"]
    assert redact("\n".join(cert), {}) == "\n".join(cert)
    chain = "\n".join([*cert[:-1], *KEY, "after"])  # a certificate without its END line, then a key
    assert redact(chain, {}) == "\n".join([*cert[:-1], "[redacted: private key]", "after"])


def test_an_empty_read_leaves_the_next_window_first():
    redactor = Redactor({})
    assert redactor.redact("") == ""
    assert redactor.redact("3q2+7wAQIDBAUGBwgJCgsMDQ4P") == "[redacted: base64 block]", "may be a key's last line"
    assert redactor.redact("-----END PRIVATE KEY-----\nok") == "[redacted: private key]\nok"
    assert Redactor({}).redact("ok\n") == "ok\n"


def test_a_begin_line_without_its_end_hides_a_bounded_number_of_lines():
    lines = ["-----BEGIN PRIVATE KEY-----", *(f"line {i}" for i in range(1000))]
    shown = redact("\n".join(lines), {}).split("\n")
    assert shown[0] == "[redacted: private key]" and "line 999" in shown and "line 5" not in shown


@pytest.mark.parametrize(
    "line", ["a." * 50000, "a-" * 50000, "Ab3+" * 25000, "s://u:" * 10000 + "@", '"password": "' + "\\" * 100000, "x:" * 50000]
)
def test_a_long_hostile_line_is_redacted_in_linear_time(line):
    started = time.perf_counter()
    redact(line, {"api/token": "s3cr3t-value"})
    assert time.perf_counter() - started < 1.0


def test_several_containers_are_labelled_one_is_not():
    assert labelled("planner", "a\nb", True) == ["[planner] a", "[planner] b"]
    assert labelled("planner", "a\nb", False) == ["a", "b"]


class FakeKube:
    def __init__(self, pods, logs, secrets=None):
        self.pods, self.logs, self.secrets, self.log_calls = pods, logs, secrets or {}, []

    def list(self, kind, namespace="", selector=""):
        if kind == "Deployment":
            return [d for d in DEPLOYMENTS if namespace in ("", d["metadata"]["namespace"])]
        instance = selector.split("=", 1)[1]
        return [p for p in self.pods if p["metadata"]["labels"]["kuberos.io/instance"] == instance]

    def get(self, kind, name, namespace):
        if name == "forbidden":
            raise PermissionError("403")
        return self.secrets.get(name)

    def log(self, pod, namespace, container="", tail_lines=None, since_seconds=None, timestamps=False, previous=False):
        self.log_calls.append((container, tail_lines, since_seconds))
        texts = self.logs[container]
        return texts.pop(0) if len(texts) > 1 else texts[0]


def _pod(instance, containers, created="2026-11-28T10:00:00Z", volumes=()):
    return {
        "metadata": {
            "name": f"{instance}-abc",
            "namespace": "kuberos-test-fleet",
            "creationTimestamp": created,
            "labels": {"kuberos.io/instance": instance},
        },
        "spec": {"nodeName": "edge-1", "containers": [{"name": c} for c in containers], "volumes": list(volumes)},
    }


def test_a_key_block_split_across_follow_polls_is_redacted_with_the_state_of_its_container():
    pods = [_pod("pnp-planner-fetch-1", ["planner", "sidecar"])]
    first = "2026-11-28T10:00:01Z key:\n2026-11-28T10:00:02Z -----BEGIN EC PRIVATE KEY-----\n2026-11-28T10:00:03Z MHcC\n"
    later = first + "2026-11-28T10:00:04Z AQEE\n2026-11-28T10:00:05Z -----END EC PRIVATE KEY-----\n2026-11-28T10:00:06Z ok\n"
    side = ["2026-11-28T10:00:01Z side\n", "2026-11-28T10:00:01Z side\n2026-11-28T10:00:04Z AQEEfine\n"]
    kube = FakeKube(pods, {"planner": [first, later], "sidecar": side})
    now = [0.0]

    def sleep(seconds):
        now[0] += seconds

    found = read_module_log(kube, "pnp", "planner", "fetch-1", follow_s=1.5, clock=lambda: now[0], sleep=sleep)
    assert found["lines"] == [
        "[planner] key:",
        "[planner] [redacted: private key]",
        "[sidecar] side",
        "[planner] [redacted: private key]",
        "[planner] ok",
        "[sidecar] AQEEfine",
    ], "each container has its own state: the sidecar's line after the planner's block is shown"


def test_a_module_log_is_read_labelled_followed_and_redacted():
    keys = [{"name": "k", "secret": {"secretName": "keys"}}]
    pods = [
        _pod("pnp-coordinator-shared-0", ["coordinator", "sidecar"], volumes=keys),
        _pod("pnp-coordinator-shared-0", ["coordinator", "sidecar"], created="2026-11-28T09:00:00Z"),
    ]
    first = "2026-11-28T10:00:01.5Z hello fetch-2\n2026-11-28T10:00:02.25Z key is hunter22\n"
    later = first + "2026-11-28T10:00:03.125Z next cycle\n"
    secrets = {"keys": {"metadata": {"name": "keys"}, "data": {"k": base64.b64encode(b"hunter22").decode()}}}
    kube = FakeKube(pods, {"coordinator": [first, later], "sidecar": ["2026-11-28T10:00:01Z side\n"]}, secrets=secrets)
    now = [0.0]

    def clock():
        return now[0]

    def sleep(seconds):
        now[0] += seconds

    found = read_module_log(kube, "pnp", "coordinator", "fetch-2", follow_s=1.5, clock=clock, sleep=sleep)
    assert found["pod"] == "pnp-coordinator-shared-0-abc" and found["node"] == "edge-1", "the newest pod"
    assert found["lines"] == [
        "[coordinator] hello fetch-2",
        "[coordinator] key is [redacted: keys/k]",
        "[sidecar] side",
        "[coordinator] next cycle",
    ]
    assert found["redacted"] == ["keys/k"]
    only = read_module_log(
        FakeKube(pods[1:], {"sidecar": ["2026-11-28T10:00:01Z side\n"]}), "pnp", "coordinator", "fetch-1", container="sidecar"
    )
    assert only["lines"] == ["side"] and only["containers"] == ["sidecar"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("pnp", "mapper", "fetch-1"), "deployment pnp has no module mapper; its modules: coordinator, planner"),
        (("pnp", "planner", "fetch-9"), "module planner of pnp runs for no robot fetch-9; it runs for: fetch-1, fetch-2"),
        (("nothing", "planner", "fetch-1"), "deployment nothing has no module running in any fleet"),
        (("pnp", "planner", "fetch-1"), "fetch-1/planner (pnp-planner-fetch-1) has no pod yet"),
    ],
)
def test_what_is_not_there_is_named(args, message):
    kube = FakeKube([], {})
    kube.list = lambda kind, namespace="", selector="": (
        [d for d in DEPLOYMENTS if "nothing" not in selector] if kind == "Deployment" else []
    )
    with pytest.raises(LogNotFound, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_module_log(kube, *args)


def test_a_secret_that_cannot_be_read_stops_the_reading_and_bad_bounds_are_refused():
    pods = [_pod("pnp-planner-fetch-1", ["planner"], volumes=[{"name": "k", "secret": {"secretName": "forbidden"}}])]
    with pytest.raises(KuberosError, match="cannot read Secret forbidden, which pnp-planner-fetch-1-abc mounts"):
        read_module_log(FakeKube(pods, {"planner": ["x"]}), "pnp", "planner", "fetch-1")
    with pytest.raises(KuberosError, match="follow must be from 0 to 600 seconds"):
        read_module_log(FakeKube(pods, {}), "pnp", "planner", "fetch-1", follow_s=601)
