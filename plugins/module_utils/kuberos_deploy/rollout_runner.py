"""Carrying out a rollout plan against a cluster, with the Kubernetes Python client (I/O; the decisions are in
``kuberos/rollout.py``).

Every object is applied with one server-side apply; a wave's gate polls the wave's pods (one list call per poll)
until each replaced instance runs exactly one pod of its new state, Running and Ready on its placed node, then
watches them for the soak window: a restart, a crash loop or a failed pod fails the gate. An optional ROS probe
command runs after the soak (non-zero exit fails the gate). On failure, every robot touched so far gets its
previous objects back, and the objects created for the rollout are removed.
"""

from __future__ import annotations

import json
import os
import subprocess
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pod_security
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import HOSTNAME, INSTANCE, MANAGED_BY
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.rollout import (
    Change,
    Downtime,
    PodState,
    Wave,
    gate_verdict,
    pod_failure,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import is_ready
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import RENDERED_KINDS, Kube, status_of
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ros.graph_check import (
    GraphCheck,
    declares_topics,
    graph_check_problem,
)

ROLLOUT_MANAGER = "kuberos-rollout"


class GateFailed(Exception):
    """A wave did not pass its health gate; the message says which instance and why."""


class Cluster:
    """The few calls a rollout makes (through the access layer): server-side apply, delete, and the pods of instances."""

    def __init__(self, clients, field_manager: str):
        self.kube = Kube(clients, field_manager)
        self.field_manager = field_manager
        self._names: dict[str, str] | None = None
        self._ready: dict[str, bool] = {}
        self._nodes_read = 0.0

    def _nodes(self) -> None:
        """Node names and readiness, read at most once a second."""
        if self._names is not None and time.monotonic() - self._nodes_read < 1.0:
            return
        items = self.kube.list("Node")
        self._names = {
            n["metadata"]["name"]: (n["metadata"].get("labels") or {}).get(HOSTNAME, n["metadata"]["name"]) for n in items
        }
        self._ready = {n["metadata"]["name"]: is_ready(n) for n in items}
        self._nodes_read = time.monotonic()

    def inventory_name(self, node: str) -> str:
        """A Kubernetes node's inventory name (its hostname label), which placements use."""
        self._nodes()
        return self._names.get(node, node)

    def node_ready(self, node: str) -> bool:
        self._nodes()
        return self._ready.get(node, False)

    def apply(self, obj: dict, dry_run: bool = False, manager: str | None = None) -> None:
        if obj["kind"] not in RENDERED_KINDS:
            raise ValueError(f"a rollout does not apply {obj['kind']}")
        if obj["kind"] == "Namespace":
            # never stricter than the namespace is: other deployments of the fleet may need its level
            obj = json.loads(json.dumps(obj))
            live = self.kube.get("Namespace", obj["metadata"]["name"]) or {}
            enforced = ((live.get("metadata") or {}).get("labels") or {}).get(pod_security.ENFORCE)
            labels = obj["metadata"].setdefault("labels", {})
            if enforced in pod_security.LEVELS and labels.get(pod_security.ENFORCE):
                labels[pod_security.ENFORCE] = pod_security.loosest([enforced, labels[pod_security.ENFORCE]])
        self.kube.apply(obj, dry_run=dry_run, manager=manager)

    def delete(self, kind: str, namespace: str, name: str) -> None:
        self.kube.delete(kind, name, namespace)

    def prestage(self, namespace: str, plan: dict[str, dict], timeout: float, parallel: int, progress) -> dict:
        """Pull each robot's new images (``RolloutPlan.prestage``) through a short-lived pod on the robot, at most
        ``parallel`` robots at a time, for at most ``timeout`` seconds in all; the pods are removed after. What was
        pulled where, and the problems (a failed pull, a robot still pulling at the timeout): the waves go on."""
        started = time.monotonic()
        waiting = list(plan)
        running: dict[str, str] = {}  # node -> its pod's name
        done: dict[str, float] = {}
        problems: list[str] = []
        try:
            while waiting or running:
                while waiting and len(running) < parallel:
                    node = waiting.pop(0)
                    pod = prestage_pod(namespace, node, plan[node])
                    try:
                        self.kube.create(pod)
                    except Exception as exc:
                        if status_of(exc) is None:
                            raise
                        problems.append(f"{node}: the prestage pod was refused ({exc.status} {exc.reason})")
                        continue
                    running[node] = pod["metadata"]["name"]
                if time.monotonic() - started > timeout:
                    problems += [f"{node}: still pulling after {timeout:g} s" for node in running]
                    problems += [f"{node}: not started within {timeout:g} s" for node in waiting]
                    break
                for node, name in list(running.items()):
                    pod = self.kube.get("Pod", name, namespace)
                    if pod is None:
                        problems.append(f"{node}: the prestage pod went away")
                        del running[node]
                        continue
                    finished, problem = prestage_verdict(pod)
                    if finished:
                        done[node] = round(time.monotonic() - started, 2)
                        if problem:
                            problems.append(f"{node}: {problem}")
                        progress(f"pre-pulled onto {node} after {done[node]:.1f} s" + (f" ({problem})" if problem else ""))
                        self._delete_pod(namespace, name)
                        del running[node]
                time.sleep(PRESTAGE_POLL_S)
        finally:
            for name in running.values():
                self._delete_pod(namespace, name)
        images = sorted({image for entry in plan.values() for image, _policy in entry["images"]})
        return {"robots": len(plan), "images": images, "seconds": round(time.monotonic() - started, 2), "done_after_s": done,
                "problems": problems}  # fmt: skip

    def _delete_pod(self, namespace: str, name: str) -> None:
        self.kube.delete("Pod", name, namespace, grace_seconds=0)

    def pods(self, namespace: str, instances: set[str]) -> dict[str, list[PodState]]:
        found: dict[str, list[PodState]] = {}
        if not instances:
            return found
        selector = f"{MANAGED_BY}=kuberos,{INSTANCE} in ({','.join(sorted(instances))})"  # only the wave's pods
        for pod in self.kube.list("Pod", namespace, selector=selector):
            meta, spec, status = pod["metadata"], pod.get("spec") or {}, pod.get("status") or {}
            instance = (meta.get("labels") or {}).get(INSTANCE)
            if instance not in instances:
                continue
            statuses = status.get("containerStatuses") or []
            waiting = next(
                (
                    ((s.get("state") or {}).get("waiting") or {}).get("reason") or ""
                    for s in statuses
                    if (s.get("state") or {}).get("waiting")
                ),
                "",
            )
            node = spec.get("nodeName") or ""
            found.setdefault(instance, []).append(
                PodState(
                    meta["name"],
                    self.inventory_name(node) if node else "",
                    status.get("phase") or "",
                    # A pod on a node that is not Ready is not serving, whatever its last reported condition.
                    is_ready(pod) and self.node_ready(node),
                    sum(s.get("restartCount") or 0 for s in statuses),
                    waiting,
                    bool(meta.get("deletionTimestamp")),
                    (spec.get("containers") or [{}])[0].get("image", ""),
                )
            )
        return found


PRESTAGE = "prestage"  # the component of the pods that pull a rollout's images onto robots before its first wave
PRESTAGE_POLL_S = 0.5
PRESTAGE_WAITING = ("ContainerCreating", "PodInitializing")  # still pulling (or about to)


def pinned_options(clients, params: dict, dep, namespace: str, bridges: bool):
    """The render options of a rollout, each image pinned to the digest its registry serves now (``pin_images``): a
    tag that moved since the deploy is an image change of this rollout, rolled out in its waves."""
    from dataclasses import replace

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import image_digests
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import render_options

    options = render_options(params)
    if not params.get("pin_images"):
        return options
    wanted = image_digests.pull_secrets([dep])
    listed = Kube(clients).list("Secret", namespace)
    secrets = [s for s in listed if (namespace, s["metadata"]["name"]) in wanted]
    digests = image_digests.for_render([dep], params, secrets, bridges)
    return replace(options, image_digests=tuple(sorted(digests.items())))


def prestage_pod(namespace: str, node: str, entry: dict) -> dict:
    """A pod on ``node`` with one container per image of ``entry`` (``RolloutPlan.prestage``): the kubelet pulls
    each as for the module's own pod; the container itself only runs ``true`` (or fails to start where the image
    has no ``true``: pulled all the same), never the module."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import COMPONENT, ROBOT_TAINT
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import dns_label

    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "metadata": {
            "name": dns_label("kuberos-prestage", node),
            "namespace": namespace,
            "labels": {MANAGED_BY: ROLLOUT_MANAGER, COMPONENT: PRESTAGE},
        },
        # restricted as every pod of the fleet's namespace: it only runs `true` to get the images onto the robot
        "spec": pod_security.harden(
            {
                "nodeSelector": {HOSTNAME: node},
                "tolerations": [{"key": ROBOT_TAINT, "operator": "Exists", "effect": "NoSchedule"}],
                "restartPolicy": "Never",
                "terminationGracePeriodSeconds": 0,
                "automountServiceAccountToken": False,
                "imagePullSecrets": [{"name": name} for name in entry["pull_secrets"]],
                "containers": [
                    {
                        "name": f"image-{index}",
                        "image": image,
                        "imagePullPolicy": policy,
                        "command": ["true"],
                        "resources": {"requests": {"cpu": "1m", "memory": "4Mi"}, "limits": {"memory": "16Mi"}},
                    }
                    for index, (image, policy) in enumerate(entry["images"])
                ],
            }
        ),
    }


def prestage_verdict(pod: dict) -> tuple[bool, str]:
    """(done, problem) of a prestage pod: done once every container's image is on the node (the kubelet created or
    ran its container, or reports its image) or its pull failed (the problem says how; the wave's gate will too)."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import IMAGE_PULL_REASONS

    statuses = {s["name"]: s for s in (pod.get("status") or {}).get("containerStatuses") or []}
    problems = []
    for container in pod["spec"]["containers"]:
        status = statuses.get(container["name"])
        if status is None:
            return False, ""
        waiting = (status.get("state") or {}).get("waiting")
        if waiting and waiting.get("reason") in IMAGE_PULL_REASONS:
            problems.append(f"{container['image']}: {waiting['reason']} {waiting.get('message') or ''}".strip())
        elif not status.get("imageID") and waiting and (waiting.get("reason") or "ContainerCreating") in PRESTAGE_WAITING:
            return False, ""
    return True, "; ".join(problems)


def _node_and_image(obj: dict) -> tuple[str, str]:
    pod = obj["spec"]["template"]["spec"]
    return next(iter((pod.get("nodeSelector") or {}).values()), ""), pod["containers"][0]["image"]


class Rollout:
    """Runs a plan's waves through their gates; rolls the touched robots back when a gate fails."""

    def __init__(self, cluster: Cluster, namespace: str, gate_timeout: float, soak_s: float, poll_s: float = 0.2,
                 ros_probe: list[str] | None = None, progress=None, update_lock: list[str] | None = None,
                 update_lock_wait: float = 120.0, graph_check=None):  # fmt: skip
        self.graph_check = graph_check  # robots -> graph_check.Verdict: the declared topics, live
        self.update_lock = update_lock or []
        self.update_lock_wait = update_lock_wait
        self.locked: dict[str, str] = {}  # robot -> why it was left pending (its update lock held, or not checkable)
        self.cluster = cluster
        self.namespace = namespace
        self.gate_timeout = gate_timeout
        self.soak_s = soak_s
        self.poll_s = poll_s
        self.ros_probe = ros_probe or []
        self.progress = progress or (lambda line: None)
        self.downtime = Downtime()
        self.applied: list[Change] = []  # in order, to undo
        self.waves_done: list[dict] = []

    # -- applying ---------------------------------------------------------------------------------
    def apply_change(self, change: Change) -> None:
        if change.action == "remove":
            self.cluster.delete(change.kind, change.namespace, change.name)
        else:
            self.cluster.apply(change.after)
        self.applied.append(change)

    def undo(self) -> list[str]:
        """Give every touched object its previous state back (newest first); objects the rollout created go."""
        undone = []
        for change in reversed(self.applied):
            if change.action == "create":
                self.cluster.delete(change.kind, change.namespace, change.name)
            elif change.before is not None:
                self.cluster.apply(change.before)
            undone.append(f"{change.kind}/{change.name}")
        self.applied = []
        return undone

    # -- the gate -----------------------------------------------------------------------------------
    def _observe(self, wanted: dict[str, tuple[str, str]]):
        observed = self.cluster.pods(self.namespace, set(wanted))
        now = time.monotonic()
        for instance in wanted:
            ready = any(p.ready and p.phase == "Running" and not p.deleting for p in observed.get(instance, []))
            self.downtime.observe(instance, ready, now)
        return observed

    def gate(self, wave: Wave, old_pods: set[str] = frozenset()) -> float:
        """Wait until the wave's instances settle, then soak; raises GateFailed. Returns the seconds it took.
        ``old_pods`` are the wave's pods from before it was applied."""
        start = time.monotonic()
        wanted = self.wanted(wave)
        deadline = start + self.gate_timeout
        pending = list(wanted)
        while True:
            observed = self._observe(wanted)
            failures, pending = gate_verdict(observed, wanted, old_pods)
            if failures:
                raise GateFailed("; ".join(failures))
            if not pending:
                break
            if time.monotonic() > deadline:
                raise GateFailed(
                    f"not Running and Ready on their placed nodes within {self.gate_timeout:g} s: {', '.join(pending)}"
                )
            time.sleep(self.poll_s)
        baseline = {
            p.name: p.restarts for pods in self._observe(wanted).values() for p in pods if not p.deleting
        }  # restarts before the soak (0 for fresh pods)
        soak_end = time.monotonic() + self.soak_s
        while time.monotonic() < soak_end:
            observed = self._observe(wanted)
            for instance, pods in sorted(observed.items()):
                for pod in pods:
                    why = pod_failure(pod, baseline.get(pod.name, 0))
                    if why is not None:
                        raise GateFailed(f"{instance}: {why} within the soak window of {self.soak_s:g} s")
                if not any(p.ready and not p.deleting for p in pods):
                    raise GateFailed(f"{instance}: no pod Ready within the soak window of {self.soak_s:g} s")
            time.sleep(self.poll_s)
        if self.ros_probe:
            self._probe(wave, sorted(wanted))
        if self.graph_check is not None:
            verdict = self.graph_check(sorted(wave.robots))
            if not verdict.ok:
                more = f"; and {len(verdict.problems) - 5} more" if len(verdict.problems) > 5 else ""
                raise GateFailed(f"the ROS graph does not connect as declared: {'; '.join(verdict.problems[:5])}{more}")
        return time.monotonic() - start

    @staticmethod
    def wanted(wave: Wave) -> dict[str, tuple[str, str]]:
        return {c.name: _node_and_image(c.after) for c in wave.changes if c.kind == "Deployment" and c.after}

    def _probe(self, wave: Wave, instances: list[str]) -> None:
        env = {
            **os.environ,
            "KUBEROS_NAMESPACE": self.namespace,
            "KUBEROS_ROBOTS": ",".join(wave.robots),
            "KUBEROS_INSTANCES": ",".join(instances),
            "KUBEROS_MODULES": ",".join(sorted({c.module for c in wave.changes})),
        }
        try:
            done = subprocess.run(self.ros_probe, env=env, capture_output=True, text=True, timeout=self.gate_timeout, check=False)
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise GateFailed(f"the ROS probe {self.ros_probe[0]} did not run: {exc}") from None
        if done.returncode != 0:
            detail = (done.stdout + done.stderr).strip().splitlines()[-3:]
            raise GateFailed(f"the ROS probe failed (exit {done.returncode}): {' | '.join(detail)}")

    def settle_back(self, instances: dict[str, tuple[str, str]]) -> list[str]:
        """After a rollback: wait (up to the gate timeout) for the previous state; the instances that did not return."""
        deadline = time.monotonic() + self.gate_timeout
        pending = list(instances)
        while pending and time.monotonic() < deadline:
            observed = self._observe(instances)
            _failures, pending = gate_verdict(observed, instances)
            if pending:
                time.sleep(self.poll_s)
        return pending

    # -- the robots' update locks ----------------------------------------------------------------------
    def held_locks(self, wave: Wave) -> dict[str, str]:
        """The wave's robots whose update lock is held (robot -> why), by the ``update_lock`` command: exit 0 none,
        1 with a ``held: <robot>`` line per robot that still holds it after waiting. A command that cannot say
        (another exit, or still running after ``update_lock_wait`` + 30 s) leaves every robot of the wave alone."""
        env = {**os.environ, "KUBEROS_NAMESPACE": self.namespace, "KUBEROS_ROBOTS": ",".join(wave.robots)}
        try:
            done = subprocess.run(self.update_lock, env=env, capture_output=True, text=True,
                                  timeout=self.update_lock_wait + 30, check=False)  # fmt: skip
        except (OSError, subprocess.TimeoutExpired) as exc:
            return dict.fromkeys(wave.robots, f"the update lock could not be checked ({exc})")
        if done.returncode == 0:
            return {}
        held = [line.split(":", 1)[1].strip() for line in done.stdout.splitlines() if line.startswith("held:")]
        if done.returncode == 1 and held:
            return {robot: "update lock held" for robot in held if robot in wave.robots}
        detail = " | ".join((done.stdout + done.stderr).strip().splitlines()[-2:])
        return dict.fromkeys(wave.robots, f"the update lock could not be checked (exit {done.returncode}: {detail})")

    def unlocked(self, wave: Wave) -> Wave:
        """``wave`` without the changes of robots that hold their update lock (they are left pending)."""
        if not self.update_lock:
            return wave
        locked = self.held_locks(wave)
        if not locked:
            return wave
        self.locked.update(locked)
        for robot, why in sorted(locked.items()):
            self.progress(f"{robot}: {why}; left pending")
        changes = [c for c in wave.changes if not set(c.robot.split(",")) & set(locked)]
        robots = tuple(r for r in wave.robots if r not in locked)
        return Wave(wave.number, wave.canary, robots, changes)

    # -- the whole plan -----------------------------------------------------------------------------
    def run(self, prepare: list[Change], waves: list[Wave]) -> dict:
        """Apply prepare, then every wave through its gate. On a failed gate: undo, and report."""
        for change in prepare:
            self.apply_change(change)
        for planned in waves:
            wave = self.unlocked(planned)
            if not wave.changes:
                continue
            label = "canary" if wave.canary else f"wave {wave.number}"
            self.progress(
                f"{label}: {len(wave.robots)} robot(s) {', '.join(wave.robots[:5])}{' ...' if len(wave.robots) > 5 else ''}"
            )
            started = time.monotonic()
            wanted = self.wanted(wave)
            old_pods = {p.name for pods in self.cluster.pods(self.namespace, set(wanted)).values() for p in pods}
            try:
                for change in wave.changes:
                    self.apply_change(change)
                self.gate(wave, old_pods)
            except GateFailed as exc:
                touched = sorted({r for w in self.waves_done for r in w["robots"]} | set(wave.robots))
                back = {
                    c.name: _node_and_image(c.before)
                    for c in self.applied
                    if c.kind == "Deployment" and c.before is not None and c.action == "update"
                }
                self.undo()
                not_back = self.settle_back(back)
                return {
                    "ok": False,
                    "failed_wave": wave.number,
                    "failed_canary": wave.canary,
                    "why": str(exc),
                    "rolled_back_robots": touched,
                    "not_back": not_back,
                    "waves": self.waves_done,
                }
            self.waves_done.append(
                {"number": wave.number, "canary": wave.canary, "robots": list(wave.robots),
                 "seconds": round(time.monotonic() - started, 2)}
            )  # fmt: skip
        return {"ok": True, "waves": self.waves_done}


# -- one rollout, end to end --------------------------------------------------------------------------
def read_record(clients, namespace: str, deployment: str):
    """The deployment's record as it is in the cluster (plain dict), with the fleet's live discovery servers."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import COMPONENT
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import discovery_from_deployments
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
        parse_record,
        pin_live_discovery,
        record_name,
    )

    kube = Kube(clients)
    configmap = kube.get("ConfigMap", record_name(deployment), namespace)
    if configmap is None:
        raise SpecError(
            [
                Problem(
                    f"deployment {deployment}",
                    "",
                    f"is not deployed in {namespace} (no record); deploy it first with playbooks/deploy.yml",
                )
            ]
        )
    record = parse_record(configmap)
    live = discovery_from_deployments(kube.list("Deployment", namespace, selector=f"{COMPONENT}=discovery-server"))
    pin_live_discovery(record, live)
    return record, configmap


def list_revisions(clients, namespace: str, deployment: str) -> list[dict]:
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import DEPLOYMENT
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import REVISION_LABEL

    items = Kube(clients).list("ConfigMap", namespace, selector=f"{DEPLOYMENT}={deployment},{REVISION_LABEL}")
    return sorted(items, key=lambda c: int(c["metadata"]["labels"][REVISION_LABEL]))


def marker(record, body: dict | None) -> dict:
    """The rollout marker on the record (applied by its own field manager; ``None`` removes it)."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import ROLLOUT_KEY

    obj = {"apiVersion": "v1", "kind": "ConfigMap", "metadata": {"name": record.name, "namespace": record.namespace}}
    if body is not None:
        obj["data"] = {ROLLOUT_KEY: json.dumps(body, sort_keys=True)}
    return obj


def _target(clients, params: dict, namespace_of):
    """The state to roll out to: a spec file (resolved against the catalog), or a kept revision of the deployment.
    Returns (deployment, spec text, source, catalog used, cause)."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import parse_revision, revision_name
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_specs

    if params.get("revision"):
        name, fleet = params["deployment"], params["fleet"]
        if not name or not fleet:
            raise SpecError([Problem("rollback", "deployment", "a rollback needs the deployment's name and fleet")])
        configmap = Kube(clients).get("ConfigMap", revision_name(name, params["revision"]), namespace_of(fleet))
        if configmap is None:
            kept = [c["data"].get("revision") for c in list_revisions(clients, namespace_of(fleet), name)]
            raise SpecError(
                [
                    Problem(
                        f"deployment {name}",
                        "revision",
                        f"{params['revision']} is not a kept revision (kept: {', '.join(kept) or 'none'})",
                    )
                ]
            ) from None
        number, _cause, dep, text, catalog = parse_revision(configmap)
        return dep, text, configmap["data"].get("source", ""), catalog, f"rollback to {number}"
    catalog = load_catalog(params["catalog"]) if params.get("catalog") else None
    deployments = load_specs(params["src"], catalog=catalog)
    if params.get("deployment"):
        deployments = [d for d in deployments if d.name == params["deployment"]]
    if len(deployments) != 1:
        names = ", ".join(d.name for d in load_specs(params["src"], catalog=catalog))
        raise SpecError(
            [Problem(params["src"], "metadata.name", f"name one deployment to roll out with deployment (the file has: {names})")]
        )
    dep = deployments[0]
    with open(params["src"], encoding="utf-8") as handle:
        text = handle.read()
    used = catalog.subset((m.catalog_module, m.version) for m in dep.modules if m.version) if catalog else None
    return dep, text, params["src"], used, "rollout"


def _reserved(clients, fleet: str, progress=None) -> dict:
    """The robot pool's reservations of ``fleet`` that hold now (robot -> Reservation); ``progress`` hears of each one
    that cannot be read (it holds nothing)."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool as robot_pool
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.robot_pool import now, reservations

    return robot_pool.held(reservations(Kube(clients), fleet, warn=progress), now())


def _graph_check(clients, params: dict, dep, namespace: str, field_manager: str, progress):
    """The gate's live graph check of ``dep`` (robots -> Verdict), or None when it declares no topics or is told not to."""
    if not params.get("graph_check", True) or not declares_topics(dep):
        return None
    check = GraphCheck.from_params(Kube(clients, field_manager), params, progress)
    return lambda robots: check.run(dep, namespace, robots)


def execute(clients, params: dict, check_mode: bool, progress) -> dict:
    """Plan a rollout of one deployment to a new state, and (unless check mode) carry it out; see the module."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import COMPONENT, DEPLOYMENT
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import render_deployment
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
        RECORD_LABEL,
        REVISION_HISTORY,
        build_records,
        module_versions,
    )
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.rollout import behind_live, plan_rollout
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import cluster_state
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import FLEET_COMPONENTS

    started = time.monotonic()
    why = graph_check_problem(params) if params.get("graph_check", True) else ""
    if why:
        raise KuberosError(why)
    dep, text, source, catalog, cause = _target(clients, params, fleet_namespace)
    namespace = fleet_namespace(dep.fleet)
    record, _configmap = read_record(clients, namespace, dep.name)
    if record.rollout:
        raise RolloutBusy(
            f"a rollout of {dep.name} to revision {record.rollout.get('revision')} is in progress since "
            f"{record.rollout.get('started')}; wait for it, or remove {record.name}'s data key rollout.json if it died"
        )
    inventory = load_inventory(params["inventory"])
    allocated = cluster_state.node_allocations(clients, [dep.name], [dep.fleet])
    unavailable = cluster_state.unavailable_nodes(clients, list(inventory.nodes))
    reserved = _reserved(clients, dep.fleet, progress)
    placement = place_modules([dep], inventory, allocated, unavailable, record.placement, reserved=reserved)
    left_out = placement.deployments[0].get("left_out") or {}
    if left_out:
        progress("left out, reserved in the robot pool: " + "; ".join(f"{r} ({why})" for r, why in sorted(left_out.items())))
    options = pinned_options(clients, params, dep, namespace, bool(placement.bridges))
    # What runs: the record's state, except the modules of robots an earlier rollout left pending while they were
    # offline (they still run the older image); robots offline now are left pending in turn.
    live = Kube(clients).list("Deployment", namespace, selector=f"{DEPLOYMENT}={dep.name}")
    before = behind_live(render_deployment(record.deployments, record.placement, record.options), live)
    after = render_deployment([dep], placement, options)
    robots = list(inventory.fleets[dep.fleet])
    offline = {r for r in robots if inventory.robots[r].node in unavailable}
    plan = plan_rollout(
        before, after, robots, params["canary"], params["wave_size"], tuple(params["canary_robots"] or ()),
        skip=lambda o: (o["metadata"].get("labels") or {}).get(COMPONENT) in FLEET_COMPONENTS,  # the fleet's, never a rollout's
        offline=offline,
    )  # fmt: skip
    current = {"revision": record.revision, "hash": record.revision_hash}
    records = build_records(
        text, source, [dep], placement, params["inventory"], options, record.field_manager, {dep.name: current}, catalog, cause
    )
    revision = int(next(o for o in records if RECORD_LABEL in o["metadata"]["labels"])["data"]["revision"])
    result = {
        "deployment": dep.name,
        "namespace": namespace,
        "revision": revision,
        "from_revision": record.revision,
        "versions": {"before": module_versions(record.spec), "after": module_versions(dep)},
        "plan": plan.to_dict(),
        "per_robot": plan.per_robot(),
        "pending_robots": list(plan.pending_robots),
        "left_out": left_out,
        "changed": plan.changed or revision != record.revision,
    }
    if plan.pending_robots:
        progress(
            f"{len(plan.pending_robots)} robot(s) offline, left pending (the next rollout run finishes them): "
            + ", ".join(plan.pending_robots)
        )
    prestage = plan.prestage()
    result["prestage_plan"] = {node: [image for image, _policy in entry["images"]] for node, entry in prestage.items()}
    if check_mode or not result["changed"]:
        return result
    cluster = Cluster(clients, record.field_manager)
    progress(f"dry run of {sum(len(w.changes) for w in plan.waves) + len(plan.prepare) + len(records)} objects")
    for change in plan.prepare + [c for w in plan.waves for c in w.changes]:
        cluster.apply(change.after, dry_run=True)
    for obj in records:
        cluster.apply(obj, dry_run=True)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    cluster.apply(
        marker(record, {"revision": revision, "from": record.revision, "instances": plan.instances(), "started": stamp}),
        manager=ROLLOUT_MANAGER,
    )
    runner = Rollout(
        cluster, namespace, params["gate_timeout"], params["soak"], ros_probe=params.get("ros_probe"), progress=progress,
        update_lock=params.get("update_lock"), update_lock_wait=params.get("update_lock_wait", 120.0),
        graph_check=_graph_check(clients, params, dep, namespace, record.field_manager, progress),
    )  # fmt: skip
    try:
        if prestage and params.get("prestage", True):
            count = len({image for entry in prestage.values() for image, _policy in entry["images"]})
            progress(f"pre-pulling {count} image(s) onto {len(prestage)} robot(s) before the first wave")
            result["prestage"] = cluster.prestage(
                namespace, prestage, params.get("prestage_timeout", 600.0), params.get("prestage_parallel", 10), progress
            )
        outcome = runner.run(plan.prepare, plan.waves)
        if outcome["ok"]:
            for obj in records:
                cluster.apply(obj)
            for change in plan.removals:
                cluster.delete(change.kind, change.namespace, change.name)
            kept = list_revisions(clients, namespace, dep.name)
            for old in kept[: max(0, len(kept) - REVISION_HISTORY)]:
                cluster.delete("ConfigMap", namespace, old["metadata"]["name"])
    finally:
        cluster.apply(marker(record, None), manager=ROLLOUT_MANAGER)
    downtime = runner.downtime.finish(time.monotonic())
    if runner.locked:
        result["locked_robots"] = dict(sorted(runner.locked.items()))
        result["pending_robots"] = sorted(set(result["pending_robots"]) | set(runner.locked))
    result.update(
        outcome,
        downtime_s=downtime,
        max_module_downtime_s=max(downtime.values(), default=0.0),
        total_s=round(time.monotonic() - started, 2),
    )
    if not outcome["ok"]:
        result["revision"] = record.revision
    return result


class RolloutBusy(KuberosError):
    """Another rollout of the deployment is in progress."""
