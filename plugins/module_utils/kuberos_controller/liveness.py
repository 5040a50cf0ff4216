"""Fast detection of a server node that died: the controller's own probe of each edge and cloud node's kubelet.

Kubernetes marks a node NotReady only when its kubelet has not renewed its Lease for the node grace period (40 s by
default; a site keeps it), so a controller that waits for that moves a dead edge server's modules 40 s late while
the robots wait for their perception and planning. The controller therefore opens a TCP connection to every server
node's kubelet port (its InternalIP, 10250) every ``interval_s``: a kubelet that stopped refuses it at once, a
machine that is gone or cut off lets it time out. ``FAILURES`` probes in a row that fail make the node down from the
first of them; one that succeeds makes it up again. The controller's grace then runs from that first failure, as
for a NotReady node (reconcile.py), so a link that blips for less than both moves nothing.

What it never does:

- probe a robot's computer: a robot that drops off the network is offline, not failed, and nothing of it moves
  (docs/connectivity.md);
- count a node down that never answered: a site whose firewall keeps the controller from kubelet ports (or a node
  with no InternalIP) is left to Kubernetes' node status alone, rather than seen as dead.

Pure over ``connect`` and ``clock``, so the rules are testable without sockets (tests/unit/test_controller_parts.py).
"""

from __future__ import annotations

import concurrent.futures
import logging
import socket
import threading
import time
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels as node_labels

log = logging.getLogger("kuberos.controller")
KUBELET_PORT = 10250
FAILURES = 3  # probes in a row that fail before a node counts as down
SERVER_ROLES = ("edge", "cloud")


def tcp_connect(address: str, port: int, timeout: float) -> bool:
    try:
        with socket.create_connection((address, port), timeout=timeout):
            return True
    except OSError:
        return False


def server_targets(nodes: list[dict]) -> dict[str, str]:
    """Kubernetes node name -> InternalIP, for the edge and cloud nodes (never a robot's computer)."""
    targets = {}
    for node in nodes:
        meta = node.get("metadata") or {}
        if (meta.get("labels") or {}).get(node_labels.ROLE) not in SERVER_ROLES:
            continue
        address = next(
            (a.get("address") for a in (node.get("status") or {}).get("addresses") or [] if a.get("type") == "InternalIP"),
            None,
        )
        if address:
            targets[meta["name"]] = address
    return targets


@dataclass
class NodeProbe:
    interval_s: float = 1.0
    port: int = KUBELET_PORT
    connect: object = tcp_connect
    clock: object = time.time
    answered: set = field(default_factory=set)  # nodes that answered at least once
    silent: set = field(default_factory=set)  # nodes said (once) never to have answered
    streak: dict = field(default_factory=dict)  # node -> (failures in a row, time of the first)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def timeout_s(self) -> float:
        return max(0.1, min(0.5, self.interval_s / 2))

    def probe(self, targets: dict[str, str]) -> bool:
        """One round over ``targets`` (node -> address), side by side. True when a node went down or came back."""
        if not targets:
            return False
        started = self.clock()
        with concurrent.futures.ThreadPoolExecutor(max_workers=min(16, len(targets))) as pool:
            results = pool.map(lambda address: self.connect(address, self.port, self.timeout_s), targets.values())
            answers = dict(zip(targets, results, strict=True))
        with self.lock:
            before = set(self._down())
            for node, ok in answers.items():
                if ok:
                    self.answered.add(node)
                    self.streak.pop(node, None)
                else:
                    count, first = self.streak.get(node, (0, started))
                    self.streak[node] = (count + 1, first)
                    if count + 1 == FAILURES and node not in self.answered and node not in self.silent:
                        self.silent.add(node)
                        log.info("node %s: its kubelet at %s:%d never answered; left to Kubernetes' node status",
                                 node, targets[node], self.port)  # fmt: skip
            for node in set(self.streak) - set(targets):
                del self.streak[node]  # gone from the cluster (or now a robot): Kubernetes' status says the rest
            after = set(self._down())
            for node in sorted(after - before):
                log.warning("node %s: its kubelet at %s:%d has not answered %d probes in a row: down", node,
                            targets.get(node, "?"), self.port, FAILURES)  # fmt: skip
            for node in sorted(before - after):
                log.info("node %s: its kubelet answers again", node)
            return after != before

    def _down(self) -> dict[str, float]:
        return {n: first for n, (count, first) in self.streak.items() if count >= FAILURES and n in self.answered}

    def down(self) -> dict[str, float]:
        """Node -> when its first failed probe in a row was sent, for the nodes that count as down now."""
        with self.lock:
            return self._down()

    def run(self, stop: threading.Event, nodes, changed: threading.Event) -> None:
        """Probe the server nodes of ``nodes()`` every ``interval_s`` until ``stop``; set ``changed`` when a node
        goes down or comes back, so that the controller's loop acts at once."""
        while not stop.is_set():
            started = time.monotonic()
            try:
                if self.probe(server_targets(nodes())):
                    changed.set()
            except Exception as exc:  # a probe round never stops the controller
                log.debug("node probe round failed: %s: %s", exc.__class__.__name__, exc)
            stop.wait(max(0.0, self.interval_s - (time.monotonic() - started)))
