"""Who may read the dashboard and ``/metrics`` in a cluster: Kubernetes bearer tokens, as kube-rbac-proxy does.

A request carries a token (``Authorization: Bearer ...``, or the session cookie a browser gets by posting its
token to ``/login``). The API server says who it is (a ``TokenReview``) and whether that user may ``get`` the
non-resource URL of the page (a ``SubjectAccessReview``: ``/kuberos/dashboard`` for the pages and their data,
``/metrics`` for the metrics). RBAC grants it with a ClusterRole such as::

    rules: [{nonResourceURLs: ["/kuberos/dashboard", "/metrics"], verbs: ["get"]}]

Answers are cached for ``ttl_s`` seconds by the token's SHA-256 (so a revoked token or binding stops working
within that time); tokens are never logged or shown, sessions live in memory only and end after ``session_s``.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import threading
import time
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, clients_of, status_of

DASHBOARD_PATH = "/kuberos/dashboard"
METRICS_PATH = "/metrics"
COOKIE = "kuberos_session"
log = logging.getLogger("kuberos.controller")


@dataclass(frozen=True)
class Verdict:
    status: int  # 200 allowed, 401 who you are is unknown, 403 not allowed, 503 the API server did not answer
    user: str = ""
    why: str = ""


class KubernetesAuth:
    def __init__(self, api_client, ttl_s: float = 60.0, session_s: float = 3600.0, largest: int = 4096):
        self.kube = Kube(clients_of(api_client))
        self.ttl_s = ttl_s
        self.session_s = session_s
        self.largest = largest
        self.lock = threading.Lock()
        self.cache: dict[tuple[str, str], tuple[float, Verdict]] = {}
        self.sessions: dict[str, tuple[str, float]] = {}  # session id -> (token, ends at)

    def check(self, token: str, path: str) -> Verdict:
        if not token or len(token) > 16384:
            return Verdict(401, why="no bearer token")
        key = (hashlib.sha256(token.encode()).hexdigest(), path)
        now = time.monotonic()
        with self.lock:
            cached = self.cache.get(key)
            if cached and cached[0] > now:
                return cached[1]
        verdict = self._ask(token, path)
        if verdict.status != 503:
            with self.lock:
                if len(self.cache) >= self.largest:
                    self.cache = {k: v for k, v in self.cache.items() if v[0] > now}
                    if len(self.cache) >= self.largest:
                        self.cache.clear()
                self.cache[key] = (now + self.ttl_s, verdict)
        return verdict

    def _ask(self, token: str, path: str) -> Verdict:
        try:
            review = self.kube.create({"apiVersion": "authentication.k8s.io/v1", "kind": "TokenReview",
                                       "spec": {"token": token}})  # fmt: skip
            status = review.get("status") or {}
            if not status.get("authenticated"):
                return Verdict(401, why="the token is not valid")
            user = status.get("user") or {}
            name = user.get("username", "")
            access = self.kube.create(
                {
                    "apiVersion": "authorization.k8s.io/v1",
                    "kind": "SubjectAccessReview",
                    "spec": {
                        "user": name,
                        "groups": user.get("groups") or [],
                        "uid": user.get("uid") or "",
                        "extra": user.get("extra") or {},
                        "nonResourceAttributes": {"path": path, "verb": "get"},
                    },
                }
            )
        except Exception as exc:  # refused, or a connection error (the API server restarting)
            if status_of(exc) is not None:
                log.warning("dashboard: token or access review failed: %s %s", exc.status, exc.reason)
            else:
                log.warning("dashboard: token or access review failed: %s", exc.__class__.__name__)
            return Verdict(503, why="the API server did not answer the review")
        if not (access.get("status") or {}).get("allowed"):
            return Verdict(403, name, f"{name} may not get {path}")
        return Verdict(200, name)

    # -- browser sessions -----------------------------------------------------------------------------
    def open_session(self, token: str) -> str:
        session = secrets.token_urlsafe(32)
        now = time.monotonic()
        with self.lock:
            self.sessions = {k: v for k, v in self.sessions.items() if v[1] > now}
            if len(self.sessions) >= self.largest:
                self.sessions.pop(next(iter(self.sessions)))
            self.sessions[session] = (token, now + self.session_s)
        return session

    def session_token(self, session: str) -> str:
        with self.lock:
            found = self.sessions.get(session or "")
        if not found or found[1] <= time.monotonic():
            return ""
        return found[0]

    def close_session(self, session: str) -> None:
        with self.lock:
            self.sessions.pop(session or "", None)
