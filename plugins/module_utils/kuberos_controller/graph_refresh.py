"""The controller keeps the dashboard's ROS graph current: while it leads, every ``every`` seconds it runs the live
graph check (``kuberos_ros.graph_check``: a short-lived pod beside one of the deployment's modules) of each
deployment whose modules declare topics, on every robot the deployment serves, one deployment at a time. Each check
rewrites the deployment's graph ConfigMap, which the dashboard's ROS graph view shows; a check that fails changes
nothing else (the controller moves modules for faults of nodes and pods, not of the graph).

Off with ``--graph-every 0`` (a site whose nodes run no containers, such as kwok nodes).
"""

from __future__ import annotations

import logging

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ros.graph_check import GraphCheck, declares_topics

log = logging.getLogger("kuberos.controller")


def checked_records(configmaps: list[dict]) -> list:
    """The records whose deployments declare topics, by namespace and name (unreadable ones left out)."""
    records = []
    for configmap in configmaps:
        try:
            record = parse_record(configmap)
        except KuberosError:
            continue
        if declares_topics(record.spec):
            records.append(record)
    return sorted(records, key=lambda r: (r.namespace, r.deployment))


class GraphRefresh:
    def __init__(self, controller, image: str, every_s: float, timeout_s: float = 30.0, window_s: float = 3.0,
                 check=None):  # fmt: skip
        self.controller = controller
        self.every_s = every_s
        self.check = check or GraphCheck(controller.kube, image, timeout_s, window_s)
        self.rounds = 0

    def once(self, stop_event) -> int:
        """One round over the deployments that declare topics; the number checked."""
        done = 0
        for record in checked_records(self.controller.records.snapshot()):
            if stop_event.is_set() or not self.controller.leading:
                break
            robots = sorted({robot for instance in record.placement.instances for robot in instance.robots})
            try:
                verdict = self.check.run(record.spec, record.namespace, robots)
            except Exception as exc:  # the fence refused (no longer leading), or the cluster did: the next round tries again
                log.warning("graph check of %s/%s not run: %s", record.namespace, record.deployment, exc)
                continue
            done += 1
            log.info("graph check of %s/%s: %s", record.namespace, record.deployment,
                     verdict.summary if verdict.ok else "; ".join(verdict.problems[:3]))  # fmt: skip
        self.rounds += 1
        return done

    def run(self, stop_event) -> None:
        while not stop_event.wait(self.every_s):
            if self.controller.leading:
                self.once(stop_event)
