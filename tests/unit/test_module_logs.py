"""A module's output without kubectl: the instance that serves a robot, Secrets kept out, several containers
labelled (plugins/module_utils/kuberos/module_logs.py and kuberos_deploy/module_log_reader.py, without a cluster)."""

from __future__ import annotations

import base64

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.module_logs import (
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
