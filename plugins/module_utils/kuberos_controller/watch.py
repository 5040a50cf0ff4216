"""The controller's watch cache: one ``Store`` per kind (list, then watch from the resourceVersion, relist after an
error or a 410 Gone), read by the controller as snapshots. Imports the Kubernetes client only when it runs."""

from __future__ import annotations

import json
import logging
import threading

log = logging.getLogger("kuberos.controller")


def store_key(obj: dict) -> tuple[str, str]:
    """(namespace, name): an object in a ``Store``, which holds one kind."""
    meta = obj["metadata"]
    return meta.get("namespace", ""), meta["name"]


class Store:
    """A watched set of objects of one kind: list, then watch, relist on errors; thread-safe reads."""

    def __init__(self, name: str, list_call, changed: threading.Event, **selector):
        self.name = name
        self.list_call = list_call
        self.selector = selector
        self.changed = changed
        self.items: dict[tuple[str, str], dict] = {}
        self.synced = threading.Event()
        self.lock = threading.Lock()
        self.errors = 0
        self.generation = 0  # bumped on every change: the dashboard rebuilds its view when any store's moves on

    def snapshot(self) -> list[dict]:
        with self.lock:
            return list(self.items.values())

    def relist(self) -> str:
        response = self.list_call(_preload_content=False, **self.selector)
        body = json.loads(response.data)
        with self.lock:
            self.items = {store_key(item): item for item in body.get("items", [])}
            self.generation += 1
        self.synced.set()
        self.changed.set()
        return body["metadata"]["resourceVersion"]

    def run(self, stop: threading.Event) -> None:
        from kubernetes.client.exceptions import ApiException
        from kubernetes.watch.watch import iter_resp_lines

        backoff = 0.2
        version = None
        while not stop.is_set():
            try:
                if version is None:
                    version = self.relist()
                    backoff = 0.2
                response = self.list_call(
                    watch=True, resource_version=version, timeout_seconds=60, allow_watch_bookmarks=True,
                    _preload_content=False, _request_timeout=90, **self.selector,
                )  # fmt: skip
                try:
                    for line in iter_resp_lines(response):
                        if stop.is_set():
                            break
                        version = self.handle(json.loads(line), version)
                        if version is None:
                            break  # 410 Gone or another error event: relist
                finally:
                    response.release_conn()
            except ApiException as exc:
                self.errors += 1
                version = None
                log.warning("watch %s: %s %s; relisting in %.1f s", self.name, exc.status, exc.reason, backoff)
                stop.wait(backoff)
                backoff = min(backoff * 2, 5.0)
            except Exception as exc:  # connection refused, reset, timeouts: the API server may be restarting
                self.errors += 1
                version = None
                log.warning("watch %s: %s; relisting in %.1f s", self.name, exc.__class__.__name__, backoff)
                stop.wait(backoff)
                backoff = min(backoff * 2, 5.0)

    def handle(self, event: dict, version: str) -> str | None:
        """Apply one watch event; returns the resourceVersion to continue from, or None to relist."""
        kind, obj = event.get("type"), event.get("object") or {}
        if kind == "ERROR":
            log.info("watch %s: %s; relisting", self.name, obj.get("message", obj))
            return None
        version = obj.get("metadata", {}).get("resourceVersion", version)
        if kind == "BOOKMARK":
            return version
        with self.lock:
            if kind == "DELETED":
                self.items.pop(store_key(obj), None)
            else:
                self.items[store_key(obj)] = obj
            self.generation += 1
        self.changed.set()
        return version
