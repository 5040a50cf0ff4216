"""The load signals that scale shared modules (``kuberos.scaling``): one value per instance, or none.

- ``cpu``: CPU use against the module's cpu request, from the Kubernetes metrics API (``metrics.k8s.io``
  PodMetrics, served by metrics-server where a cluster has one). Without that API there is no value, and the
  module holds its instance count (the status says so).
- a module's own gauge (any other ``metric``): read from every instance's Ready pod, either straight from the pod
  (``http://<pod IP>:<metricsPort>/metrics``, the Prometheus text format; the default) or, when the controller is
  given ``--prometheus-url``, from that Prometheus with the query ``max by (namespace, pod) (<metric>{namespace=
  "<fleet namespace>"})``: where the cluster's Prometheus already scrapes the modules (a PodMonitor), and where the
  controller cannot reach pod addresses.

Every read is bounded by a timeout; a pod that does not answer gives no value (never an error of the pass).
"""

from __future__ import annotations

import http.client
import json
import logging
import re
import urllib.parse

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scaling import gauge_value
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, clients_of, status_of
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.bounded import (
    Deadline,
    ReadBoundExceeded,
    exchange,
)

log = logging.getLogger("kuberos.controller.signals")
TIMEOUT_S = 2.0
MAX_ANSWER = 4 * 1024 * 1024  # a pod's /metrics page or a Prometheus answer
_CPU_USAGE = re.compile(r"^([0-9.]+)(n|u|m|)\Z")


def cpu_millis(usage: str) -> float:
    """A metrics API CPU usage (``'12345678n'``, ``'250m'``, ``'1'``) in millicores."""
    found = _CPU_USAGE.match(str(usage).strip())
    if not found:
        raise ValueError(f"not a CPU usage: {usage!r}")
    number, unit = float(found.group(1)), found.group(2)
    return number * {"n": 1e-6, "u": 1e-3, "m": 1.0, "": 1000.0}[unit]


def _get(url: str, timeout: float) -> bytes:
    """GET over plain HTTP (a pod's /metrics, a Prometheus query): at most ``MAX_ANSWER`` bytes within ``timeout``
    seconds in all (however slowly it trickles); OSError unless 200, or when a bound is exceeded (naming it)."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https"):
        raise ValueError(f"not an http(s) URL: {url}")
    connection_class = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
    where = f"{parts.hostname}:{parts.port}" if parts.port else str(parts.hostname)
    with Deadline(where, timeout) as deadline:
        connection = connection_class(parts.hostname, parts.port, timeout=timeout)
        try:
            status, _headers, body = exchange(
                connection, deadline, "GET", parts.path + (f"?{parts.query}" if parts.query else ""), where, MAX_ANSWER
            )
            if status != 200:
                raise OSError(f"{url}: HTTP {status}")
            return body
        except ReadBoundExceeded as exc:
            raise OSError(str(exc)) from None
        except (http.client.HTTPException, OSError) as exc:
            if deadline.expired:
                raise OSError(str(deadline.error())) from None
            raise OSError(f"{url}: {exc}") from exc
        finally:
            connection.close()


class Signals:
    """Reads one signal per instance. ``pods``: instance name -> its Ready pod (a plain pod dict)."""

    def __init__(self, api_client=None, prometheus_url: str = "", timeout: float = TIMEOUT_S):
        self.api_client = api_client
        self.prometheus_url = prometheus_url.rstrip("/")
        self.timeout = timeout
        self.metrics_api = True  # False once the cluster said it has no metrics API (checked again every 5 minutes)
        self.metrics_api_checked = 0.0

    def values(self, namespace: str, policy, pods: dict[str, dict], requests_millis: float, now: float) -> dict[str, float]:
        if policy.uses_cpu:
            return self._cpu(namespace, pods, requests_millis, now)
        if self.prometheus_url:
            return self._prometheus(namespace, policy.metric, pods)
        return self._scrape(policy, pods)

    def _scrape(self, policy, pods: dict[str, dict]) -> dict[str, float]:
        found = {}
        for instance, pod in pods.items():
            ip = (pod.get("status") or {}).get("podIP")
            if not ip:
                continue
            host = f"[{ip}]" if ":" in ip else ip
            try:
                text = _get(f"http://{host}:{policy.metrics_port}/metrics", self.timeout).decode("utf-8", "replace")
            except (OSError, ValueError) as exc:
                log.debug("no metrics from %s (%s): %s", instance, ip, exc)
                continue
            value = gauge_value(text, policy.metric)
            if value is not None:
                found[instance] = value
        return found

    def _prometheus(self, namespace: str, metric: str, pods: dict[str, dict]) -> dict[str, float]:
        query = f'max by (namespace, pod) ({metric}{{namespace="{namespace}"}})'
        url = f"{self.prometheus_url}/api/v1/query?{urllib.parse.urlencode({'query': query})}"
        try:
            answer = json.loads(_get(url, self.timeout))
        except (OSError, ValueError) as exc:
            log.warning("Prometheus query for %s failed: %s", metric, exc)
            return {}
        by_pod = {}
        for series in (answer.get("data") or {}).get("result") or []:
            try:
                by_pod[series["metric"]["pod"]] = float(series["value"][1])
            except (KeyError, IndexError, TypeError, ValueError):
                continue
        return {inst: by_pod[pod["metadata"]["name"]] for inst, pod in pods.items() if pod["metadata"]["name"] in by_pod}

    def _cpu(self, namespace: str, pods: dict[str, dict], requests_millis: float, now: float) -> dict[str, float]:
        if self.api_client is None or requests_millis <= 0:
            return {}
        if not self.metrics_api and now - self.metrics_api_checked < 300:
            return {}
        self.metrics_api_checked = now
        try:
            listed = Kube(clients_of(self.api_client)).pod_metrics(namespace, timeout=self.timeout)
        except Exception as exc:
            if status_of(exc) in (404, 503):
                if self.metrics_api:
                    log.warning("the cluster serves no metrics API (metrics.k8s.io: %s); cpu scaling holds", exc.status)
                self.metrics_api = False
                return {}
            raise
        self.metrics_api = True
        usage = {}
        for item in listed:
            try:
                usage[item["metadata"]["name"]] = sum(cpu_millis(c["usage"]["cpu"]) for c in item.get("containers") or [])
            except (KeyError, TypeError, ValueError):
                continue
        return {
            inst: usage[pod["metadata"]["name"]] / requests_millis
            for inst, pod in pods.items()
            if pod["metadata"]["name"] in usage
        }
