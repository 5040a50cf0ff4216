"""One deploy pass, for the ``rosdeployment`` module: spec + inventory -> validate, read the cluster once, place,
render, dry-run every object server-side, apply what changes (one server-side-apply PATCH per object, from a thread
pool), prune, wait until every module runs where it was placed.

The I/O around the pure core: the core (``kuberos/``) parses, places and renders; this file reads and writes the
cluster through the Kubernetes Python client and writes the render directory. Every object is read once (one LIST per
kind and namespace), dry-run once and, only when the dry run says the cluster would hold something else, applied once.
"""

from __future__ import annotations

import datetime
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import naming, pod_security
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool as robot_pool
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.applied import applied_of, owns, unchanged
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.batch import is_batch_document
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.diff import (
    change_summary,
    clean_object,
    object_diff,
    record_changes,
    summary_text,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import COMPONENT, DEPLOYMENT, MANAGED_BY, MODULE
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import bridge_secret_name
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import fleet_namespace, object_key, object_label
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.quantities import parse_cpu, parse_memory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import record_name, record_placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import (
    file_reader,
    load_rosdeployments,
    name_clash_problems,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import compare, deploy_table
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.yaml_source import load_documents, read_text
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import (
    node_allocations,
    previous_placement,
    running_modules,
    stale_objects,
    unavailable_nodes,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_dir import RenderDirError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_pass import render_to_dir
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import (
    REFUSALS,
    RENDERED_KINDS,
    Kube,
    api_clients,
    bearer_clients,
    refusal,
    status_of,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ros.graph_check import (
    GraphCheck,
    declares_topics,
    graph_check_problem,
)

CLUSTER_HINT = 'in the inventory (docs/inventory.md, "Third-party clusters")'


# Seconds an image problem that is not yet final (the kubelet has failed the pull once) may last before the deploy's
# wait gives up on it anyway: the kubelet tries again after 10-15 s, and a second pull of a large image takes a while.
PULL_PROBLEM_LIMIT = 120.0


def keep_pod_security_levels(namespaces: list[dict], objects: list[dict], live: dict, stale: list[dict]) -> None:
    """Loosen each rendered Namespace's enforced Pod Security level to admit the pods of the Deployments already
    there that this pass neither renders nor removes (another RosDeployment of the fleet, deployed from another
    file): labelling the namespace for this file's pods alone would refuse theirs the next time one is replaced."""
    ours = {object_key(o) for o in objects} | {object_key(o) for o in stale}
    for namespace in namespaces:
        name = namespace["metadata"]["name"]
        labels = namespace["metadata"]["labels"]
        others = [
            pod_security.level(spec)[0]
            for key, obj in live.items()
            if key[0] == "Deployment" and key[1] == name and key not in ours
            if (spec := pod_security.pod_spec_of(obj)) is not None
        ]
        if labels.get(pod_security.ENFORCE) and others:
            labels[pod_security.ENFORCE] = pod_security.loosest([labels[pod_security.ENFORCE], *others])


def remote_clients(name: str, connection: dict | None):
    """Typed clients for a third-party cluster, reached through its API server with a bearer token and its CA."""
    connection = connection or {}
    if not connection.get("api_server") or not connection.get("token"):
        raise KuberosError(
            f"Cluster {name} needs kuberos_api_server, kuberos_token (in ansible-vault) and kuberos_ca_cert {CLUSTER_HINT}."
        )
    return bearer_clients(connection["api_server"], connection["token"], connection.get("ca_cert"))


@dataclass
class Target:
    """One cluster's share of a deploy: its namespaces and other objects, what is live there, what the dry run said."""

    api: Kube
    namespaces: list[dict]
    objects: list[dict]
    live: dict = field(default_factory=dict)  # object_key -> live object
    existing: set = field(default_factory=set)  # namespace names that exist
    created: list = field(default_factory=list)  # namespaces this pass created
    after: dict = field(default_factory=dict)  # object_key -> what the cluster would hold (dry run), or as rendered

    @property
    def label(self) -> str:
        return f" (cluster {self.api.name})" if self.api.name else ""

    read_namespaces: set = field(default_factory=set)  # namespaces whose objects are in ``live``

    def read(self, pool: ThreadPoolExecutor, namespaces: set | None = None) -> None:
        """Every object of the kinds KubeROS applies in ``namespaces`` (default: the target's), one LIST per kind and
        namespace; namespaces read before are not read again."""
        wanted = (namespaces if namespaces is not None else self.wanted_namespaces) - self.read_namespaces
        if not wanted:
            return
        found = self.api.list("Namespace")
        self.existing = {n["metadata"]["name"] for n in found}
        self.live.update((object_key(n), n) for n in found if n["metadata"]["name"] in wanted)
        jobs = [(kind, ns) for ns in sorted(wanted & self.existing) for kind in RENDERED_KINDS if kind != "Namespace"]
        for items in pool.map(lambda job: self.api.list(*job), jobs):
            self.live.update((object_key(o), o) for o in items)
        self.read_namespaces |= wanted

    @property
    def wanted_namespaces(self) -> set:
        return {n["metadata"]["name"] for n in self.namespaces} | {
            o["metadata"]["namespace"] for o in self.objects if o["metadata"].get("namespace")
        }

    def all_objects(self) -> list[dict]:
        return self.namespaces + self.objects

    def managed(self, namespace: str) -> list[dict]:
        """The live objects KubeROS manages in ``namespace``, in the light form ``stale_objects`` reads."""
        out = []
        for (kind, ns, _name), obj in sorted(self.live.items()):
            labels = obj["metadata"].get("labels") or {}
            if ns == namespace and kind != "Namespace" and labels.get(MANAGED_BY) == "kuberos":
                out.append(
                    {
                        "apiVersion": obj["apiVersion"],
                        "kind": kind,
                        "metadata": {"name": obj["metadata"]["name"], "namespace": ns, "labels": dict(labels)},
                    }
                )
        return out


class NotReady(KuberosError):
    """The deploy applied its objects, but not every module was Ready on its placed node in time; ``result`` is the
    deploy's result (what changed, the rows, the problems)."""

    def __init__(self, message: str, result: dict):
        super().__init__(message)
        self.result = result


class DeployPass:
    """The ``rosdeployment`` module's work, in one call (``run``); ``params`` are its options, ``check_mode`` and
    ``diff_mode`` Ansible's. The spec file is read and parsed once; what it holds flows through placement,
    rendering, the dry run, the apply, the record and the wait."""

    def __init__(self, params: dict, check_mode: bool, diff_mode: bool):
        self.params = params
        self.check_mode = check_mode
        self.diff_mode = diff_mode
        self.workers = max(1, int(params.get("workers") or 8))
        self.timings: dict[str, float] = {}
        self.pool_warnings: list[str] = []  # the robot pool's reservations that cannot be read (they hold nothing)
        self._started = time.monotonic()

    def _lap(self, step: str) -> None:
        now = time.monotonic()
        self.timings[step] = round(now - self._started, 3)
        self._started = now

    # --- reading ---------------------------------------------------------------------------------------------------

    def run(self) -> dict:
        """Deploy (or undeploy, or render only) the spec file, or run the batch job it holds; the module's result."""
        why = graph_check_problem(self.params) if self.params.get("graph_check") else ""
        if why:
            raise KuberosError(why)
        self.load()
        if self.batch:
            return self._batch()
        if self.params["state"] == "absent":
            result = self.undeploy()
            if self.diff_mode:
                result["diff"] = {"before": "".join(f"{r}\n" for r in result["removed"]), "after": ""}
            return {**result, "timings": self.timings}
        if not self.params["apply"]:
            self.previous, self.allocated, self.unavailable = {}, dict(self.params["allocated"]), {}
            self.place()
            self.render()
            result = {"changed": self.rendered["changed"], "table": self.rendered["table"]}
            if self.diff_mode:
                result["diff"] = self.rendered["plan"].diff()
        else:
            result = self._apply()
        left_out = {d["name"]: d["left_out"] for d in self.placement.deployments if d.get("left_out")}
        return {
            **result,
            "left_out": left_out,
            "notes": [note for dep in self.deployments for note in dep.notes] + self.pool_warnings,
            "placement": self.placement.to_dict(),
            "dest": self.rendered["dest"],
            "files": self.rendered["files"],
            "timings": self.timings,
        }

    def _apply(self) -> dict:
        try:
            self.read_cluster()
        except KuberosError:
            raise
        except Exception:
            # A cluster that cannot be read: a spec that cannot be placed even on empty nodes says so first.
            self.previous, self.allocated, self.unavailable = {}, {}, {}
            self.place()
            raise
        self.place()
        self.pin_images()
        self.render()
        rendered = self.rendered
        result = self.deploy()
        diffs = result.pop("diffs")
        if self.diff_mode:
            result["diff"] = [{"prepared": result["summary"] + "\n\n"}, *diffs]
        result["changed"] = result["changed"] or rendered["changed"]
        if self.check_mode:
            result["table"] = rendered["table"]
            return result
        timeout = self.params["wait_timeout"]
        waited = self.wait() if timeout else {"rows": [], "ready": True, "table": rendered["table"]}
        result.update(waited)
        if not waited["ready"]:
            waiting = [
                f"{r['robot']}/{r['module']}: {r['phase']} on {r['node'] or '-'}" + (f" ({r['note']})" * bool(r["note"]))
                for r in waited["rows"]
                if not r["ready"]
            ]
            msg = f"not every module is Ready on its placed node after {timeout} s: "
            if waited["problems"]:
                stuck = [f"{r['robot']}/{r['module']}" for r in waited["rows"] if r["problem"] and not r["ready"]]
                msg = f"{', '.join(stuck[:10])} cannot start: {'; '.join(waited['problems'][:5])}. Not Ready: "
            raise NotReady(msg + "; ".join(waiting[:10]), {**result, "timings": self.timings})
        checked = [d for d in self.deployments if declares_topics(d)] if self.params.get("graph_check") else []
        if checked:
            verdicts = self.check_graph(checked)
            result["graph"] = {name: verdict.to_dict() for name, verdict in verdicts.items()}
            failed = [f"{name}: {line}" for name, verdict in verdicts.items() for line in verdict.problems]
            if failed:
                shown = "; ".join(failed[:8]) + (f"; and {len(failed) - 8} more" if len(failed) > 8 else "")
                raise NotReady(f"the ROS graph does not connect as declared: {shown}", {**result, "timings": self.timings})
        return result

    def check_graph(self, deployments) -> dict:
        """The live graph check of each deployment that declares topics, on the robots it was placed for."""
        check = GraphCheck.from_params(Kube(self.clients, self.params["field_manager"]), self.params)
        verdicts = {}
        for dep in deployments:
            robots = sorted({r for inst in self.placement.instances if inst.deployment == dep.name for r in inst.robots})
            verdicts[dep.name] = check.run(dep, fleet_namespace(dep.fleet), robots)
        self._lap("graph_check")
        return verdicts

    def _batch(self) -> dict:
        """A batch job given to the deploy: run it (or, with apply false, render it) as playbooks/batch.yml does."""
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.batch_runner import remove_batch, run_batch

        params = {**self.params, "poll": 2.0}
        if params["state"] == "absent":
            return {"changed": False} if self.check_mode else remove_batch(api_clients(params["kubeconfig"]), params)
        progress = []
        result = run_batch(
            lambda: api_clients(params["kubeconfig"]), params, self.check_mode, progress.append, documents=self.documents
        )
        outcome = "\n".join(progress + result.get("failures", []))
        return {**result, "progress": progress, "table": result["plan"] + ("\n\n" + outcome if outcome else ""), "batch": True}

    def load(self) -> None:
        """Read the spec file once: its documents are either batch jobs (run as ``playbooks/batch.yml`` does) or
        deployments, parsed from the same documents, with the catalog and the inventory."""
        params = self.params
        self.spec_text = read_text(params["src"], params["src"])  # read once: parsed here, kept in the record
        self.documents = load_documents(self.spec_text, params["src"])
        data = [d.data for d in self.documents if d.data is not None]
        self.batch = bool(data) and all(is_batch_document(d) for d in data)
        if self.batch:
            return
        self.catalog = load_catalog(params["catalog"]) if params.get("catalog") else None
        self.deployments = load_rosdeployments(
            self.spec_text, params["src"], self.catalog, file_reader(params["src"]), documents=self.documents
        )
        self.inventory = load_inventory(params["inventory"])
        self._lap("validate")

    def read_cluster(self) -> None:
        """What runs on each node, which nodes are unavailable, what this deployment runs now (sticky placement)."""
        self.clients = api_clients(self.params["kubeconfig"])
        names = [d.name for d in self.deployments]
        fleets = [d.fleet for d in self.deployments]
        self.local = Target(Kube(self.clients, self.params["field_manager"]), [], [])
        with ThreadPoolExecutor(max_workers=self.workers) as pool:  # the reads are independent: side by side
            reads = [
                pool.submit(node_allocations, self.clients, names, fleets),
                pool.submit(unavailable_nodes, self.clients, list(self.inventory.nodes)),
                pool.submit(previous_placement, self.clients, [{"name": d.name, "fleet": d.fleet} for d in self.deployments]),
            ]
            # Every object of the fleets' namespaces, read now so that a name clash stops the deploy before it renders.
            self.local.read(pool, {naming.fleet_namespace(d.fleet) for d in self.deployments})
            allocated, self.unavailable, self.previous = (read.result() for read in reads)
        for node, extra in (self.params.get("allocated") or {}).items():
            entry = allocated.setdefault(node, {"cpu": "0m", "memory": 0, "gpu": 0, "pods": 0})
            entry["cpu"] = f"{parse_cpu(str(entry['cpu'])) + parse_cpu(str(extra.get('cpu', '0')))}m"
            entry["memory"] = parse_memory(str(entry["memory"])) + parse_memory(str(extra.get("memory", "0")))
            entry["gpu"] = int(entry["gpu"]) + int(extra.get("gpu", 0))
            entry["pods"] = int(entry["pods"]) + int(extra.get("pods", 0))
        self.allocated = allocated
        self._check_names(self.local)
        self.cluster_read = True
        self._lap("read the cluster")

    def pin_images(self) -> None:
        """Each image that names no digest resolved to the one its registry serves now (``pin_images``), asked with
        the credentials of the pull secrets the modules name (read with the fleets' objects); render then writes
        ``image@digest``. Nothing is applied when an image cannot be resolved."""
        if not self.params.get("pin_images"):
            return
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import image_digests

        wanted = image_digests.pull_secrets(self.deployments)
        secrets = [obj for (kind, ns, name), obj in self.local.live.items() if kind == "Secret" and (ns, name) in wanted]
        digests = image_digests.for_render(self.deployments, self.params, secrets, bool(self.placement.bridges))
        self.params = {**self.params, "image_digests": digests}
        self._lap("pin images")

    def reservations(self) -> dict:
        """The robot pool's reservations that hold now, from the fleets' objects read (robot -> Reservation); None
        when no cluster was read (a render only). One that cannot be read holds nothing: its warning joins the notes."""
        if not getattr(self, "cluster_read", False):
            return None
        found = [obj for (kind, _ns, _name), obj in self.local.live.items()
                 if kind == "ConfigMap" and (obj["metadata"].get("labels") or {}).get(robot_pool.LABEL) == "true"]  # fmt: skip
        readable, self.pool_warnings = robot_pool.read(found)
        return robot_pool.held(readable, datetime.datetime.now(datetime.UTC))

    def place(self) -> None:
        previous = self.previous if (self.previous.get("instances") or self.previous.get("discovery")) else None
        self.placement = place_modules(
            self.deployments,
            self.inventory,
            self.allocated,
            self.unavailable,
            Placement.from_dict(previous) if previous else None,
            reserved=self.reservations(),
        )
        self._lap("place")

    def render(self) -> None:
        params = self.params
        revisions = dict(self.previous.get("revisions") or {})
        try:
            self.rendered = render_to_dir(
                params,
                self.deployments,
                self.placement,
                self.catalog,
                self.check_mode,
                revisions=revisions,
                spec_text=self.spec_text,
                clusters=self.inventory.clusters,
                model=self.inventory,
            )
        except OSError as exc:
            raise RenderDirError(f"cannot write the render directory {params['dest']}: {exc}") from exc
        self._lap("render")

    # --- the cluster -----------------------------------------------------------------------------------------------

    def targets(self) -> list[Target]:
        """This cluster's share first, then each third-party cluster's."""
        rendered = self.rendered
        local_secrets, remote_secrets = self._secret_objects()
        self.local.namespaces = rendered["namespaces"]
        self.local.objects = rendered["apply_objects"] + local_secrets
        out = [self.local]
        for cluster, share in sorted(rendered["remote"].items()):
            connection = (self.params.get("clusters") or {}).get(cluster)
            api = Kube(remote_clients(cluster, connection), self.params["field_manager"], cluster)
            out.append(Target(api, share["namespaces"], share["apply_objects"] + remote_secrets.get(cluster, [])))
        return out

    def _secret_objects(self) -> tuple[list[dict], dict[str, list[dict]]]:
        """The bridges' TLS Secrets as render made them (none yet in check mode before their certificates exist)."""
        local, remote = [], {}
        for entry in self.rendered["secrets"]:
            if entry["secret"] is not None:
                (remote.setdefault(entry["cluster"], []) if entry["cluster"] else local).append(entry["secret"])
        return local, remote

    def _dry_run(self, target: Target, pool: ThreadPoolExecutor) -> dict[str, str]:
        """Dry-run every object of ``target`` whose namespace exists; the others are new. Returns the refusals."""
        refused = {}

        manager = self.params["field_manager"]

        def one(obj):
            namespace = obj["metadata"].get("namespace")
            if namespace and namespace not in target.existing:
                return obj, obj, None  # a new namespace in check mode: no dry run can be done there; the object is new
            live = target.live.get(object_key(obj))
            if unchanged(obj, live, manager):
                return obj, live, None  # applied as it is rendered, and nobody changed it since: an apply changes nothing
            try:
                return obj, target.api.apply(obj, dry_run=True), None
            except Exception as exc:
                if status_of(exc) not in REFUSALS:
                    raise
                return obj, None, refusal(exc)

        for obj, after, why in pool.map(one, target.all_objects()):
            if why is not None:
                refused[object_label(obj) + target.label] = why
            else:
                target.after[object_key(obj)] = after
        return refused

    def _create_namespaces(self, target: Target) -> None:
        for namespace in target.namespaces:
            name = namespace["metadata"]["name"]
            if name not in target.existing:
                target.api.apply(namespace, dry_run=False)
                target.created.append(name)
                target.existing.add(name)

    def _undo_namespaces(self, targets: list[Target]) -> None:
        for target in targets:
            for name in target.created:
                target.api.delete("Namespace", name)

    def _needs_apply(self, target: Target, obj: dict) -> bool:
        key = object_key(obj)
        live = target.live.get(key)
        if live is None or clean_object(live) != clean_object(target.after[key]):
            return True
        if applied_of(live) != applied_of(target.after[key]):
            return True  # the same content, applied before it carried what it was applied as (kuberos.applied)
        # The same content under another field manager: apply, so that KubeROS owns (and later prunes) its fields.
        return not owns(live, self.params["field_manager"])

    def _stale(self, target: Target) -> list[dict]:
        names = [d.name for d in self.deployments]
        keep = target.all_objects()
        stale = []
        for fleet in sorted({d.fleet for d in self.deployments}):
            namespace = naming.fleet_namespace(fleet)
            stale.extend(stale_objects(target.managed(namespace), keep, names, remove_discovery=True))
        return stale

    def deploy(self) -> dict:
        """The pass against the cluster(s), after ``render``. Raises ``KuberosError`` when the cluster refuses."""
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            targets = self.targets()
            for target in targets:
                target.read(pool)
            self._lap("read the objects")
            stale = self._stale(targets[0])
            for target in targets:
                keep_pod_security_levels(target.namespaces, target.objects, target.live, stale if target is targets[0] else [])
            refused = {}
            try:
                for target in targets:
                    if not self.check_mode:
                        self._create_namespaces(target)
                    refused.update(self._dry_run(target, pool))
            except BaseException:
                if not self.check_mode:
                    self._undo_namespaces(targets)
                raise
            self._lap("dry run")
            summary, diffs, counts = self._summary(targets, stale, refused)
            if refused:
                if not self.check_mode:
                    self._undo_namespaces(targets)
                raise KuberosError(
                    "The cluster rejected the deployment in a server-side dry run; nothing was applied.\n"
                    + "\n".join(f"{what}: {why}" for what, why in sorted(refused.items()))
                    + "\n\n"
                    + summary
                )
            changes = [(t, o) for t in targets for o in t.all_objects() if object_key(o) in t.after and self._needs_apply(t, o)]
            applied, removed = [], [f"{o['kind']}/{o['metadata']['namespace']}/{o['metadata']['name']}" for o in stale]
            if not self.check_mode:
                for target, obj in changes:  # namespaces first: they exist before the objects in them are applied
                    if obj["kind"] == "Namespace":
                        target.api.apply(obj, dry_run=False)
                rest = [(t, o) for t, o in changes if o["kind"] != "Namespace"]
                list(pool.map(lambda pair: pair[0].api.apply(pair[1], dry_run=False), rest))
                applied = [object_label(o) + t.label for t, o in changes]
                self._lap("apply")
                list(pool.map(targets[0].api.delete_object, stale))
                self._lap("prune")
            else:
                applied = [object_label(o) + t.label for t, o in changes]
        created = [name + t.label for t in targets for name in t.created]
        return {
            "changed": bool(changes or created or stale or (self.check_mode and counts["new"])),
            "applied": applied,
            "created_namespaces": created,
            "removed": removed,
            "refused": refused,
            "summary": summary,
            "objects": counts,
            "diffs": diffs,
        }

    def _check_names(self, target: Target) -> None:
        """Stop when a module would take the name of an object another deployment owns (a-b + c = a + b-c)."""
        live = []
        for (kind, namespace, name), obj in target.live.items():
            if kind in ("Deployment", "ConfigMap"):
                labels = obj["metadata"].get("labels") or {}
                live.append(
                    {
                        "kind": kind,
                        "namespace": namespace,
                        "name": name,
                        "deployment": labels.get(DEPLOYMENT, ""),
                        "module": labels.get(MODULE, ""),
                    }
                )
        fleets = self.inventory.fleets
        problems = name_clash_problems(self.deployments, lambda dep: dep.robots or fleets.get(dep.fleet), live)
        if problems:
            raise SpecError(problems, title=f"{self.params['src']} would take the names of objects in the cluster")

    def _summary(self, targets: list[Target], stale: list[dict], refused: dict) -> tuple[str, list[dict], dict]:
        """What changes, module by module of each robot and object by object (live against dry run)."""
        local = targets[0]
        pairs = {}
        for target in targets:
            for obj in target.all_objects():
                key = object_key(obj)
                if key in target.after:
                    pairs[key if not target.api.name else (*key[:2], f"{key[2]}@{target.api.name}")] = (
                        target.live.get(key),
                        target.after[key],
                    )
        removed = [local.live[object_key(o)] for o in stale if object_key(o) in local.live]
        counts = {"changed": 0, "new": 0, "removed": 0, "unchanged": 0}
        diffs = []
        for before, after in [*pairs.values(), *((o, None) for o in removed)]:
            entry = object_diff(before, after)
            if entry is None:
                counts["unchanged"] += 1
                continue
            counts["new" if before is None else "removed" if after is None else "changed"] += 1
            diffs.append(entry)
        previous = {}
        for dep in self.deployments:
            record = local.live.get(("ConfigMap", naming.fleet_namespace(dep.fleet), record_name(dep.name)))
            previous[dep.name] = record_placement(record) if record is not None else None
        rows = change_summary(previous, self.placement, pairs)
        text = summary_text(rows, record_changes(pairs), counts, self.check_mode, refused=refused)
        return text, diffs, counts

    def wait(self) -> dict:
        """Until every module runs on its placed node (or ``wait_timeout``): the table read back from the cluster.
        A pod whose image the kubelet has failed to pull twice ends the wait (``problems``, the kubelet's latest
        words): waiting longer does not help. The first failure alone is not final: a pull secret created just before
        the deploy may not have reached the kubelet's cache yet (the same problem lasting PULL_PROBLEM_LIMIT seconds
        ends the wait too)."""
        placement = self.placement.to_dict()
        fleets = [d["fleet"] for d in placement["deployments"]]
        names = [d["name"] for d in placement["deployments"]]
        deadline = time.monotonic() + int(self.params.get("wait_timeout") or 0)
        stuck_since: dict[str, float] = {}
        while True:
            rows = compare(placement, running_modules(self.clients, fleets, names))
            ready = all(r["ready"] for r in rows)
            now = time.monotonic()
            stuck = {r["pod"]: r for r in rows if r["problem"] and not r["ready"]}
            stuck_since = {pod: stuck_since.get(pod, now) for pod in stuck}
            problems = sorted({r["problem"] for r in stuck.values()})
            final = any(r["problem_final"] or now - stuck_since[pod] >= PULL_PROBLEM_LIMIT for pod, r in stuck.items())
            if ready or now >= deadline or final:
                break
            time.sleep(0.5)
        self._lap("wait")
        return {"rows": rows, "ready": ready, "table": deploy_table(rows), "problems": problems}

    # --- undeploy ----------------------------------------------------------------------------------------------------

    def undeploy(self) -> dict:
        """Every object of the deployments, here and in third-party clusters; a fleet's shared objects (discovery
        servers, bridge server, catalog) go with its last deployment."""
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import render_remote
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import BRIDGE_CLIENT
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import render_options

        self.clients = api_clients(self.params["kubeconfig"])
        self.placement = place_modules(self.deployments, self.inventory)  # names the fleets and bridges
        names = [d.name for d in self.deployments]
        local = Kube(self.clients, self.params["field_manager"])
        removed = []
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            if self.placement.bridges:
                remote = render_remote(self.deployments, self.placement, self.inventory.clusters, render_options(self.params))
                for cluster, objects in sorted(remote.items()):
                    connection = (self.params.get("clusters") or {}).get(cluster)
                    api = Kube(remote_clients(cluster, connection), self.params["field_manager"], cluster)
                    gone = [o for o in reversed(objects) if o["kind"] != "Namespace"]
                    gone += [
                        {"kind": "Secret", "metadata": {"name": bridge_secret_name(BRIDGE_CLIENT), "namespace": b.namespace}}
                        for bridges in self.placement.bridges.values()
                        for b in bridges
                        if b.cluster == cluster
                    ]
                    namespaces = {o["metadata"]["namespace"] for o in gone}
                    kinds = [k for k in RENDERED_KINDS if k != "Namespace"]
                    live = {object_key(o) for ns in namespaces for k in kinds for o in api.list(k, ns)}
                    gone = [o for o in gone if object_key(o) in live]
                    removed += [f"{object_label(o)} (cluster {cluster})" for o in gone]
                    if not self.check_mode:
                        list(pool.map(api.delete_object, gone))
            for fleet in sorted({d.fleet for d in self.deployments}):
                namespace = naming.fleet_namespace(fleet)
                target = Target(local, [], [])
                for kind in RENDERED_KINDS:
                    if kind != "Namespace":
                        target.live.update((object_key(o), o) for o in local.list(kind, namespace))
                live = target.managed(namespace)
                others = [
                    o
                    for o in live
                    if o["metadata"]["labels"].get(COMPONENT) == "ros-module"
                    and o["metadata"]["labels"].get(DEPLOYMENT) not in names
                ]
                stale = stale_objects(live, [], names, remove_discovery=not others)
                removed += [f"{o['kind']}/{namespace}/{o['metadata']['name']}" for o in stale]
                if not self.check_mode:
                    list(pool.map(local.delete_object, stale))
        self._lap("remove")
        return {"changed": bool(removed), "removed": removed}
