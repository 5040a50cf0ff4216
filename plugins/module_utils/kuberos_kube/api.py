"""The one way the collection talks to Kubernetes: typed clients from a kubeconfig, one table of the kinds it
reads and writes, and get, list, apply (server-side, stamped with the digest of what it sent: ``kuberos.applied``),
patch, create, replace, delete and log that answer in plain JSON, as the API server sent it, and treat a missing
object one way: ``get`` gives None, ``list`` gives [] for a namespace that is gone, ``delete`` gives False for an
object already gone. ``message`` turns any failure to talk to a cluster into one sentence.

Used by deploy, diff, prune, rollout, batch, status (``kuberos_deploy``), the controller and the lab. The clients
are the Kubernetes Python client's typed APIs; answers are read with ``_preload_content=False``, so no model
objects are built. A test gives ``Kube`` its own ``clients`` (objects with the typed clients' method names).
"""

from __future__ import annotations

import functools
import json
import os
import threading
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.applied import stamped
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import FIELD_MANAGER
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import object_key
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.bounded import (
    Deadline,
    ReadBoundExceeded,
    read_capped,
)

APPLY_TYPE = "application/apply-patch+yaml"
# The argument every module that talks to a cluster takes (documented by the kuberos.platform.cluster fragment).
KUBECONFIG_ARG = {"kubeconfig": {"type": "path", "required": True}}
REFUSALS = (400, 403, 409, 422)  # an object the cluster would not take (invalid, forbidden by a policy, a conflict)
START_HINT = "start the local cluster with `make cluster`, or set kuberos_kubeconfig to your cluster's kubeconfig"


VERBS = ("read", "list", "patch", "create", "delete", "replace")


@dataclass(frozen=True)
class Kind:
    """How the typed clients reach a kind: the client (``api``), the method suffix, whether it is namespaced, and
    the verbs the API server serves for it (a review is only created)."""

    api: str
    method: str
    namespaced: bool
    api_version: str
    verbs: tuple = VERBS


KINDS = {
    "Namespace": Kind("core", "namespace", False, "v1"),
    "Node": Kind("core", "node", False, "v1"),
    "ConfigMap": Kind("core", "config_map", True, "v1"),
    "Service": Kind("core", "service", True, "v1"),
    "Secret": Kind("core", "secret", True, "v1"),
    "Pod": Kind("core", "pod", True, "v1"),
    "Event": Kind("core", "event", True, "v1"),
    "Deployment": Kind("apps", "deployment", True, "apps/v1"),
    "Job": Kind("batch", "job", True, "batch/v1"),
    "NetworkPolicy": Kind("networking", "network_policy", True, "networking.k8s.io/v1"),
    "Lease": Kind("coordination", "lease", True, "coordination.k8s.io/v1"),
    "ClusterRole": Kind("rbac", "cluster_role", False, "rbac.authorization.k8s.io/v1"),
    "ClusterRoleBinding": Kind("rbac", "cluster_role_binding", False, "rbac.authorization.k8s.io/v1"),
    # who a bearer token is, and whether it may read a path (the dashboard's authentication)
    "TokenReview": Kind("authentication", "token_review", False, "authentication.k8s.io/v1", ("create",)),
    "SubjectAccessReview": Kind("authorization", "subject_access_review", False, "authorization.k8s.io/v1", ("create",)),
    # who the caller is, as the API server says (Kubernetes 1.28+): the robot pool records it with a reservation
    "SelfSubjectReview": Kind("authentication", "self_subject_review", False, "authentication.k8s.io/v1", ("create",)),
}
# The resource metrics API (metrics-server): a pod's CPU use, for scaling on cpu.
POD_METRICS = ("metrics.k8s.io", "v1beta1", "pods")
# What KubeROS renders for a deployment (applied, diffed, pruned, rolled out), in the order they are applied.
RENDERED_KINDS = ("Namespace", "ConfigMap", "Service", "Secret", "Deployment", "NetworkPolicy")
# What KubeROS keeps inside a fleet's namespace (its label selector finds them for prune, undeploy and status).
MANAGED_KINDS = ("Deployment", "Service", "ConfigMap", "Secret", "NetworkPolicy")


@dataclass(frozen=True)
class Bounds:
    """An overall deadline (seconds) for each request and a size cap (bytes) for each answer."""

    deadline_s: float
    max_bytes: int


# A cluster KubeROS does not run (a third-party cluster, reached by its inventory name) and the metrics API
# (metrics-server, an aggregated API) answer within these; the site's own API server is trusted as it is.
REMOTE_BOUNDS = Bounds(60.0, 64 * 1024 * 1024)
METRICS_BOUNDS = Bounds(10.0, 16 * 1024 * 1024)
_ACTIVE = threading.local()  # the Deadline of the request this thread is making, if bounded


class ClusterUnreachable(Exception):
    """The cluster cannot be reached; the message says which and what to do."""


def api_clients(kubeconfig: str) -> dict:
    """The typed clients of the cluster ``kubeconfig`` names, by the names ``KINDS`` uses."""
    from kubernetes import config

    if not os.path.exists(kubeconfig):
        raise ClusterUnreachable(f"no kubeconfig at {kubeconfig}; {START_HINT}")
    api = config.new_client_from_config(config_file=kubeconfig)
    return clients_of(api)


def bearer_clients(host: str, token: str, ca_cert: str | None = None) -> dict:
    """The typed clients of the API server at ``host``, reached with a bearer token (and trusting ``ca_cert``)."""
    from kubernetes import client

    configuration = client.Configuration()
    configuration.host = host
    configuration.api_key = {"authorization": token}
    configuration.api_key_prefix = {"authorization": "Bearer"}
    configuration.verify_ssl = True
    if ca_cert:
        configuration.ssl_ca_cert = ca_cert
    return clients_of(client.ApiClient(configuration))


@functools.cache
def _watched_pools() -> dict:
    """urllib3's pool classes whose connections register their sockets with the thread's active ``Deadline`` (a new
    socket when it is opened, a kept-alive one when it is taken from the pool), so a deadline ends a blocked read at
    once. Made once (urllib3 is imported only when a cluster is used)."""
    from urllib3.connection import HTTPConnection, HTTPSConnection
    from urllib3.connectionpool import HTTPConnectionPool, HTTPSConnectionPool

    def watch(sock) -> None:
        deadline = getattr(_ACTIVE, "deadline", None)
        if deadline is not None and sock is not None:
            deadline.watch(sock)

    class Watched:
        def _new_conn(self):
            sock = super()._new_conn()
            watch(sock)
            return sock

    class WatchedPool:
        def _get_conn(self, timeout=None):
            conn = super()._get_conn(timeout)
            watch(getattr(conn, "sock", None))
            return conn

    http_conn = type("WatchedHTTPConnection", (Watched, HTTPConnection), {})
    https_conn = type("WatchedHTTPSConnection", (Watched, HTTPSConnection), {})
    return {
        "http": type("WatchedHTTPConnectionPool", (WatchedPool, HTTPConnectionPool), {"ConnectionCls": http_conn}),
        "https": type("WatchedHTTPSConnectionPool", (WatchedPool, HTTPSConnectionPool), {"ConnectionCls": https_conn}),
    }


def _bounded_pools(api) -> None:
    """The connections of ``api`` can be bounded (``_watched_pools``)."""
    manager = getattr(getattr(api, "rest_client", None), "pool_manager", None)
    if manager is not None and hasattr(manager, "pool_classes_by_scheme"):
        manager.pool_classes_by_scheme = _watched_pools()


def clients_of(api) -> dict:
    """The typed clients over one ``kubernetes.client.ApiClient`` (its connections can be bounded: ``Bounds``)."""
    from kubernetes import client

    _bounded_pools(api)
    return {
        "core": client.CoreV1Api(api),
        "apps": client.AppsV1Api(api),
        "batch": client.BatchV1Api(api),
        "networking": client.NetworkingV1Api(api),
        "coordination": client.CoordinationV1Api(api),
        "rbac": client.RbacAuthorizationV1Api(api),
        "authentication": client.AuthenticationV1Api(api),
        "authorization": client.AuthorizationV1Api(api),
        "custom": client.CustomObjectsApi(api),
    }


def status_of(exc: BaseException) -> int | None:
    """The HTTP status of an API server's refusal (the typed clients' ApiException), else None."""
    status = getattr(exc, "status", None)
    return status if isinstance(status, int) and hasattr(exc, "body") else None


def refusal(exc) -> str:
    """What the API server said, in one line (its Status message when it sent one)."""
    try:
        return json.loads(exc.body).get("message") or f"{exc.status} {exc.reason}"
    except (TypeError, ValueError, AttributeError):
        return f"{exc.status} {exc.reason}"


def message(exc: BaseException, kubeconfig: str = "") -> str:
    """One sentence for a failure to talk to a cluster: unreachable, refused, or what the API server said."""
    from urllib3.exceptions import HTTPError

    where = kubeconfig or "(no kubeconfig)"
    if isinstance(exc, (ClusterUnreachable, ReadBoundExceeded)):
        return str(exc)
    if status_of(exc) is not None:
        return f"the API server refused: {exc.status} {exc.reason}: {(exc.body or '')[:500]}"
    if isinstance(exc, (HTTPError, OSError)):
        reason = getattr(exc, "reason", None) or exc
        return f"the cluster of {where} is not reachable ({reason}); {START_HINT}"
    return f"cannot use the cluster of {where}: {exc}"


class Kube:
    """Reads and writes of the kinds in ``KINDS`` through the typed clients, as plain JSON.

    ``name`` is '' for this cluster, else the third-party cluster's inventory name (for messages).
    ``timeout`` (seconds, or a callable giving them before each write) bounds each write: the controller's fence
    gives its lease's remaining time there, and refuses a write it may not make by raising. ``read_timeout``
    (seconds) bounds each read. ``bounds``: an overall deadline and a size cap for every request and answer
    (``REMOTE_BOUNDS`` by default for a third-party cluster: one that is named)."""

    def __init__(self, clients: dict, field_manager: str = FIELD_MANAGER, name: str = "", timeout=None, read_timeout=None,
                 bounds: Bounds | None = None):  # fmt: skip
        self.clients = clients
        self.field_manager = field_manager
        self.name = name
        self.timeout = timeout
        self.read_timeout = read_timeout
        self.bounds = bounds if bounds is not None else (REMOTE_BOUNDS if name else None)

    def _answer(self, call, *args, bounds: Bounds | None = None, **kwargs) -> bytes:
        """The body of ``call(*args, **kwargs)`` (a typed client's method, ``_preload_content=False``), within
        ``bounds`` (else this Kube's) when there are any: ReadBoundExceeded names the cluster and the limit."""
        bounds = bounds or self.bounds
        if bounds is None:
            return call(*args, **kwargs).data
        where = f"cluster {self.name}" if self.name else "the API server"
        with Deadline(where, bounds.deadline_s) as deadline:
            _ACTIVE.deadline = deadline
            try:
                response = call(*args, **kwargs)
                try:
                    return read_capped(response, where, bounds.max_bytes, deadline)
                finally:
                    getattr(response, "release_conn", lambda: None)()
            except Exception:
                deadline.check()
                raise
            finally:
                _ACTIVE.deadline = None

    def _method(self, kind: str, verb: str):
        found = KINDS.get(kind)
        if found is None:
            raise ValueError(f"KubeROS does not handle a {kind}")
        client = self.clients.get(found.api)
        if client is None:
            raise ValueError(f"no {found.api} client for a {kind}")
        if verb == "list_all":
            return getattr(client, f"list_{found.method}_for_all_namespaces")
        return getattr(client, f"{verb}_{'namespaced_' if found.namespaced else ''}{found.method}")

    def _where(self, kind: str, name: str, namespace: str) -> tuple:
        return (name, namespace) if KINDS[kind].namespaced else (name,)

    def _at(self, obj: dict) -> tuple:
        """Where ``obj`` is, as the typed clients' methods take it: (name, namespace), or (name,)."""
        kind, namespace, name = object_key(obj)
        return self._where(kind, name, namespace)

    def _reads(self) -> dict:
        return {} if self.read_timeout is None else {"_request_timeout": self.read_timeout}

    def _limits(self) -> dict:
        timeout = self.timeout() if callable(self.timeout) else self.timeout
        return {} if timeout is None else {"_request_timeout": timeout}

    def _head(self, kind: str) -> dict:
        return {"kind": kind, "apiVersion": KINDS[kind].api_version}

    def list_call(self, kind: str):
        """The typed client's LIST of ``kind`` (in all namespaces for a namespaced kind), for a watch of its own."""
        return self._method(kind, "list_all" if KINDS[kind].namespaced else "list")

    def get(self, kind: str, name: str, namespace: str = "") -> dict | None:
        """One object, or None when there is no such object (or namespace)."""
        try:
            data = self._answer(self._method(kind, "read"), *self._where(kind, name, namespace), _preload_content=False,
                                **self._reads())  # fmt: skip
        except Exception as exc:
            if status_of(exc) == 404:
                return None
            raise
        return {**self._head(kind), **json.loads(data)}

    def list(self, kind: str, namespace: str = "", selector: str = "", field_selector: str = "") -> list[dict]:
        """Every object of ``kind`` (in ``namespace``; in all namespaces when a namespaced kind is given none), with
        apiVersion and kind set; [] when the namespace is gone."""
        query = {"label_selector": selector} if selector else {}
        if field_selector:
            query["field_selector"] = field_selector
        query.update(self._reads())
        namespaced = kind in KINDS and KINDS[kind].namespaced
        try:
            if namespaced and not namespace:
                data = self._answer(self._method(kind, "list_all"), _preload_content=False, **query)
            else:
                data = self._answer(self._method(kind, "list"), *((namespace,) if namespaced else ()), _preload_content=False,
                                    **query)  # fmt: skip
        except Exception as exc:
            if status_of(exc) == 404:
                return []
            raise
        head = self._head(kind)  # first, as the server writes single objects
        return [{**head, **item} for item in json.loads(data).get("items") or []]

    def apply(self, obj: dict, dry_run: bool = False, manager: str | None = None) -> dict:
        """Server-side apply of ``obj`` (its fields owned by ``manager``, conflicts forced), stamped with the digest of
        what was applied (``kuberos.applied``); what the server holds."""
        extra = {"dry_run": "All"} if dry_run else {}
        data = self._answer(
            self._method(obj["kind"], "patch"),
            *self._at(obj),
            stamped(obj),  # plain data: the client serialises nothing else
            field_manager=manager or self.field_manager,
            force=True,
            _content_type=APPLY_TYPE,
            _preload_content=False,
            **extra,
            **self._limits(),
        )
        return json.loads(data)

    def patch(self, kind: str, name: str, namespace: str, patch, content_type: str | None = None) -> dict:
        """A merge (or ``content_type``) patch of one object; what the server holds."""
        extra = {"_content_type": content_type} if content_type else {}
        data = self._answer(
            self._method(kind, "patch"), *self._where(kind, name, namespace), patch, _preload_content=False, **extra,
            **self._limits(),
        )  # fmt: skip
        return json.loads(data)

    def replace(self, obj: dict) -> dict:
        """Replace ``obj`` as a whole (its ``resourceVersion`` makes the API server refuse a stale one: 409)."""
        data = self._answer(
            self._method(obj["kind"], "replace"), *self._at(obj), json.loads(json.dumps(obj)), _preload_content=False,
            **self._limits(),
        )  # fmt: skip
        return json.loads(data)

    def create(self, obj: dict) -> dict:
        """Create ``obj``; the API server's refusal (409 when it exists) is raised."""
        meta = obj.get("metadata") or {}
        args = (meta["namespace"],) if KINDS[obj["kind"]].namespaced else ()
        body = json.loads(json.dumps(obj))
        data = self._answer(self._method(obj["kind"], "create"), *args, body, _preload_content=False, **self._limits())
        return json.loads(data)

    def delete(self, kind: str, name: str, namespace: str = "", grace_seconds: int | None = None) -> bool:
        """Delete one object (its dependents in the background); False when it was already gone."""
        extra = {} if grace_seconds is None else {"grace_period_seconds": grace_seconds}
        try:
            self._answer(
                self._method(kind, "delete"), *self._where(kind, name, namespace), propagation_policy="Background",
                _preload_content=False, **extra, **self._limits(),
            )  # fmt: skip
        except Exception as exc:
            if status_of(exc) == 404:
                return False
            raise
        return True

    def delete_object(self, obj: dict) -> bool:
        """``delete`` of the object ``obj`` names (its kind, namespace and name)."""
        kind, namespace, name = object_key(obj)
        return self.delete(kind, name, namespace)

    def pod_metrics(self, namespace: str, timeout: float | None = None) -> list[dict]:
        """The resource metrics API's PodMetrics of ``namespace`` (the API server's refusal, 404 or 503 where no
        metrics-server serves it, is raised)."""
        group, version, plural = POD_METRICS
        extra = {} if timeout is None else {"_request_timeout": timeout}
        bounds = METRICS_BOUNDS if timeout is None else Bounds(float(timeout), METRICS_BOUNDS.max_bytes)
        data = self._answer(
            self.clients["custom"].list_namespaced_custom_object, group, version, namespace, plural,
            _preload_content=False, bounds=bounds, **extra,
        )  # fmt: skip
        return json.loads(data).get("items") or []

    def log(self, pod: str, namespace: str, container: str = "", tail_lines: int | None = None, since_seconds: int | None = None,
            timestamps: bool = False, previous: bool = False) -> str:  # fmt: skip
        """What a pod's container printed (the kubelet's log; the API server's refusal is raised): the last
        ``tail_lines``, those of the last ``since_seconds``, each after its RFC 3339 time with ``timestamps``, the
        previous container's (before its last restart) with ``previous``."""
        extra = {"container": container} if container else {}
        if tail_lines is not None:
            extra["tail_lines"] = tail_lines
        if since_seconds is not None:
            extra["since_seconds"] = max(1, int(since_seconds))
        if timestamps:
            extra["timestamps"] = True
        if previous:
            extra["previous"] = True
        data = self._answer(self.clients["core"].read_namespaced_pod_log, pod, namespace, _preload_content=False, **extra)
        return data.decode("utf-8", errors="replace")
