"""The one Kubernetes access layer (kuberos_kube.api), without a cluster: its kind table against the typed clients,
a missing object treated one way, server-side apply as the API server expects it, errors as one sentence."""

from __future__ import annotations

import json

import pytest
from kubernetes import client
from kubernetes.client.exceptions import ApiException
from urllib3.exceptions import MaxRetryError

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import applied
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube import api

CLIENTS = {
    "core": client.CoreV1Api,
    "apps": client.AppsV1Api,
    "batch": client.BatchV1Api,
    "networking": client.NetworkingV1Api,
    "coordination": client.CoordinationV1Api,
    "rbac": client.RbacAuthorizationV1Api,
    "authentication": client.AuthenticationV1Api,
    "authorization": client.AuthorizationV1Api,
}


@pytest.mark.parametrize("kind", sorted(api.KINDS))
def test_every_kind_reaches_methods_the_typed_clients_have(kind):
    entry = api.KINDS[kind]
    typed = CLIENTS[entry.api]
    scope = "namespaced_" if entry.namespaced else ""
    for verb in entry.verbs:
        assert hasattr(typed, f"{verb}_{scope}{entry.method}"), f"{typed.__name__} lacks {verb}_{scope}{entry.method}"
    if entry.namespaced and "list" in entry.verbs:
        assert hasattr(typed, f"list_{entry.method}_for_all_namespaces")
    assert set(api.RENDERED_KINDS) | set(api.MANAGED_KINDS) <= set(api.KINDS)


class Response:
    def __init__(self, body):
        self.data = json.dumps(body).encode()


class Recorder:
    """A typed client's methods: records each call, answers ``answers[name]`` (an exception is raised)."""

    def __init__(self, answers=None):
        self.calls, self.answers = [], answers or {}

    def __getattr__(self, name):
        def call(*args, **kwargs):
            self.calls.append((name, args, kwargs))
            answer = self.answers.get(name, {"items": []})
            if isinstance(answer, BaseException):
                raise answer
            return Response(answer)

        return call


def missing():
    return ApiException(status=404, reason="Not Found")


def test_a_missing_object_is_none_an_empty_list_or_false():
    core = Recorder(
        {"read_namespaced_config_map": missing(), "list_namespaced_secret": missing(), "delete_namespaced_pod": missing()}
    )
    kube = api.Kube({"core": core})
    assert kube.get("ConfigMap", "record", "fleet") is None
    assert kube.list("Secret", "gone") == []
    assert kube.delete("Pod", "p", "fleet") is False


def test_other_refusals_are_raised():
    core = Recorder({"read_namespaced_config_map": ApiException(status=403, reason="Forbidden")})
    with pytest.raises(ApiException):
        api.Kube({"core": core}).get("ConfigMap", "record", "fleet")


def test_list_sets_kind_and_api_version_and_spans_namespaces_when_given_none():
    apps = Recorder({"list_deployment_for_all_namespaces": {"items": [{"metadata": {"name": "a"}}]}})
    kube = api.Kube({"apps": apps})
    assert kube.list("Deployment", selector="x=y") == [{"kind": "Deployment", "apiVersion": "apps/v1", "metadata": {"name": "a"}}]
    assert apps.calls[0][2] == {"_preload_content": False, "label_selector": "x=y"}


def test_apply_is_a_forced_server_side_apply_by_the_field_manager_with_the_write_timeout():
    networking = Recorder({"patch_namespaced_network_policy": {"ok": True}})
    kube = api.Kube({"networking": networking}, "kuberos-deploy", timeout=lambda: 2.5)
    obj = {"kind": "NetworkPolicy", "apiVersion": "networking.k8s.io/v1", "metadata": {"name": "n", "namespace": "f"}}
    assert kube.apply(obj, dry_run=True) == {"ok": True}
    name, args, kwargs = networking.calls[0]
    assert (name, args[:2]) == ("patch_namespaced_network_policy", ("n", "f"))
    # what was applied, stamped with the digest of that configuration (kuberos.applied)
    assert args[2] == applied.stamped(obj) and args[2]["metadata"]["annotations"][applied.APPLIED] == applied.applied_hash(obj)
    assert kwargs == {
        "field_manager": "kuberos-deploy",
        "force": True,
        "_content_type": "application/apply-patch+yaml",
        "_preload_content": False,
        "dry_run": "All",
        "_request_timeout": 2.5,
    }


def test_a_fence_that_refuses_stops_the_write_before_it_is_sent():
    class NotLeader(Exception):
        pass

    def fence():
        raise NotLeader

    core = Recorder({"read_namespaced_pod": {"metadata": {"name": "p"}}})
    with pytest.raises(NotLeader):
        api.Kube({"core": core}, timeout=fence).delete("Pod", "p", "f")
    assert core.calls == []
    # reads are not writes: the fence does not stand in their way
    assert api.Kube({"core": core}, timeout=fence).get("Pod", "p", "f")["metadata"] == {"name": "p"}


def test_cluster_scoped_kinds_take_no_namespace():
    core = Recorder({"read_namespace": {"metadata": {"name": "f"}}})
    api.Kube({"core": core}).get("Namespace", "f")
    assert core.calls[0][:2] == ("read_namespace", ("f",))


def test_an_unknown_kind_or_a_missing_client_is_said():
    with pytest.raises(ValueError, match="does not handle a CronJob"):
        api.Kube({}).get("CronJob", "x", "y")
    with pytest.raises(ValueError, match="no apps client for a Deployment"):
        api.Kube({"core": Recorder()}).get("Deployment", "x", "y")


def test_failures_become_one_sentence():
    refused = ApiException(status=422, reason="Unprocessable Entity")
    refused.body = json.dumps({"message": "spec.replicas: Invalid value"})
    assert api.refusal(refused) == "spec.replicas: Invalid value"
    assert api.message(refused, "k").startswith("the API server refused: 422 Unprocessable Entity")
    assert api.status_of(refused) == 422 and api.status_of(OSError("x")) is None
    down = MaxRetryError(None, "https://127.0.0.1:1", reason="Connection refused")
    assert api.message(down, "/tmp/kc") == (f"the cluster of /tmp/kc is not reachable (Connection refused); {api.START_HINT}")
    assert api.message(api.ClusterUnreachable("no kubeconfig at /x"), "/x") == "no kubeconfig at /x"
    assert api.message(ValueError("odd"), "") == "cannot use the cluster of (no kubeconfig): odd"
    with pytest.raises(api.ClusterUnreachable, match="no kubeconfig at /nonexistent"):
        api.api_clients("/nonexistent")
