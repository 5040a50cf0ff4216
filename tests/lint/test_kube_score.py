"""kube-score over the manifests the collection renders from every example: no CRITICAL finding but those ignored here.

Each example is rendered as the collection renders it on the embedded site (inventories/local, its software catalog):
a RosDeployment as the ``rosdeployment_render`` module does (``render_pass.render_to_dir``: manifests, deployment
records, the bridges' TLS Secrets), a batch job as ``rosbatchjob`` does without applying (``batch_runner``). kube-score
(built from its Go module by roles/local_cluster/files/build-kube-score.sh, which ``make test`` runs) then scores the
manifests of each target cluster on their own: a third-party cluster's objects share names with this cluster's, and
kube-score keys what it scores by kind, namespace and name.

kube-score runs with its default checks (no optional ones), for the Kubernetes version of the local control plane.
A check in ``IGNORED`` does not apply to these objects; one in ``PENDING`` fires today and goes away with the issue
it names.
Both are left out with ``--ignore-test``; an entry that no longer fires on any example fails
``test_ignored_checks_still_fire``, so the lists never hide more than they say.
"""

from __future__ import annotations

import collections
import glob
import json
import os
import subprocess

import pytest
import yaml
from helpers import ROOT, built_program

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import batch
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, device_options
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_and_place
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import batch_runner
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import RENDER_ARGS
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_dir import apply_plan
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_pass import render_to_dir

pytestmark = pytest.mark.lint

BUILD = os.path.join(ROOT, "roles", "local_cluster", "files", "build-kube-score.sh")
CATALOG = os.path.join(ROOT, "inventories", "local", "catalog")

# Every example: the top-level ones (RosDeployments, one of them from the software catalog), the batch jobs and the
# reference-format files (an ApplicationDeployment and a BatchJob). None is skipped; examples/reference/config and
# examples/reference/site are not examples but what they read (a parameter file, a reference site's inventory).
TOP_LEVEL = sorted(glob.glob(os.path.join(ROOT, "examples", "*.yml")))
EXAMPLES = TOP_LEVEL + sorted(glob.glob(os.path.join(ROOT, "examples", "batch", "*.yml")))
EXAMPLES += sorted(glob.glob(os.path.join(ROOT, "examples", "reference", "*.yml")))

# examples/partner-cloud.yml runs its planner in a third-party cluster, which inventories/local does not register: it
# is added as docs/inventory.md ("Third-party clusters") shows, serving test-fleet.
PARTNER = {"kuberos_latency_ms": 30, "kuberos_fleets": ["test-fleet"], "kuberos_bridge_endpoint": "203.0.113.10"}

# Checks that do not apply to the objects the collection renders.
IGNORED = {
    "container-image-pull-policy": "IfNotPresent is the deliberate default (docs/rosdeployment.md, pullPolicy per "
    "registry): a robot offline must restart its onboard pods from the images it holds, and images named by digest "
    "cannot change under a tag.",
    "container-ephemeral-storage-request-and-limit": "A RosDeployment's resources are cpu, memory and gpu only, so "
    "there is no ephemeral-storage amount to render, and a limit nobody asked for would evict a module whose logs grow.",
    "container-security-context-user-group-id": "Pods run as user and group 1000 (pod_security.DEFAULT_USER), which "
    "kube-score calls low (it wants more than 10000): 1000 is the first user of the published ROS images (ubuntu) and "
    "of the project's, who owns what their workspaces install; not root is what the restricted level asks, and holds.",
    "container-security-context-readonlyrootfilesystem": "A ROS module writes where its packages expect (its "
    "workspace, ~/.ros, Python caches), so the collection does not make a user's root filesystem read-only; the "
    "restricted level does not ask for it (the controller's own pod is read-only).",
}

# Options of kube-score's own that drop one part of a check rather than the whole (so container-resources still asks
# for requests and a memory limit).
OPTIONS = {
    "--ignore-container-cpu-limit": "CPU is requested for the placement but never limited, so the CFS quota does not "
    "throttle ROS control loops in their bursts; memory is limited at its request.",
}

# Checks that fire today and are being fixed: none now. An entry names the issue that removes it.
PENDING: dict[str, str] = {}

# Findings an example asks for in its spec, by (example, check, object): kube-score is right, and the example means it.
ASKED = {
    (
        "reference/talker-listener.kuberos.yml",
        "container-security-context-privileged",
        "Deployment kuberos-test-fleet/talker-listener-talker-fetch-1",
    ): "Its talker module asks for privilege: true (the reference format's requirements.privilege, for the gripper, a "
    "host device), which renders a privileged container.",
}

# The kinds kube-score scores: each rendered object of these kinds must come back scored (none merged or dropped).
SCORED_KINDS = {
    "CronJob", "DaemonSet", "Deployment", "HorizontalPodAutoscaler", "Ingress", "Job", "NetworkPolicy", "Pod",
    "PodDisruptionBudget", "Service", "StatefulSet",
}  # fmt: skip
CRITICAL = 1  # kube-score's grades: 1 critical, 5 warning, 7 almost OK, 10 OK


def kubernetes_version() -> str:
    """v1.34 from the local control plane's version (roles/local_cluster/defaults/main.yml)."""
    with open(os.path.join(ROOT, "roles", "local_cluster", "defaults", "main.yml"), encoding="utf-8") as handle:
        full = yaml.safe_load(handle)["local_cluster_kubernetes_version"]
    return ".".join(full.split(".")[:2])


def example_id(path: str) -> str:
    return os.path.relpath(path, os.path.join(ROOT, "examples"))


@pytest.fixture(scope="module")
def kube_score() -> str:
    """The kube-score program of the cache (build-kube-score.sh)."""
    return built_program(BUILD, "kube-score")


@pytest.fixture(scope="module")
def site(local_raw) -> dict:
    raw = {**local_raw, "hosts": {**local_raw["hosts"], "partner-cloud": dict(PARTNER)}}
    raw["groups"] = {**local_raw["groups"], "clusters": ["partner-cloud"]}
    return raw


def render(path: str, raw: dict, dest: str) -> dict[str, list[str]]:
    """The example's manifests rendered into ``dest``, by target cluster ("" is this one): their files."""
    with open(path, encoding="utf-8") as handle:
        documents = [d for d in yaml.safe_load_all(handle) if d is not None]
    if any(batch.is_batch_document(d) for d in documents):
        job, inventory = batch_runner.load({"src": path, "inventory": raw})
        slots = batch_runner.place(job, inventory)
        objects = batch.render_batch(job, slots, RenderOptions(**device_options(inventory)))
        apply_plan(batch_runner.plan_render(dest, job, objects, batch_runner.plan_rows(job, slots)))
        clusters = {"": os.path.join(dest, "manifests")}
        secrets = []
    else:
        catalog = load_catalog(CATALOG)
        deployments, placement = load_and_place(path, raw, catalog=catalog)
        params = {"src": path, "dest": dest, "inventory": raw, "field_manager": "kuberos"}
        params.update({name: spec["default"] for name, spec in RENDER_ARGS.items()})
        rendered = render_to_dir(params, deployments, placement, catalog, False, clusters=load_inventory(raw).clusters)
        clusters = {"": os.path.join(dest, "manifests")}
        clusters.update({c: os.path.join(dest, "clusters", c) for c in rendered["remote"]})
        secrets = rendered["secret_files"]
    files = {
        cluster: sorted(glob.glob(os.path.join(folder, "**", "*.yaml"), recursive=True)) for cluster, folder in clusters.items()
    }
    for secret in secrets:
        files[secret["cluster"]].append(secret["path"])
    assert files[""], f"{example_id(path)} rendered no manifests into {dest}"
    return files


def score(program: str, files: list[str], ignore: bool = True) -> list[dict]:
    """kube-score's scored objects for ``files`` (its JSON report: each object's checks, with their ids and grades)."""
    command = [program, "score", "--output-format", "json", "--color", "never", "--kubernetes-version", kubernetes_version()]
    if ignore:
        command += list(OPTIONS)
        for check in sorted({**IGNORED, **PENDING}):
            command += ["--ignore-test", check]
    result = subprocess.run([*command, *files], capture_output=True, text=True, timeout=300)
    # exit 1 is also what a CRITICAL finding gives: the report tells them apart
    try:
        return json.loads(result.stdout) or []  # null: nothing kube-score scores
    except json.JSONDecodeError:
        pytest.fail(f"kube-score (exit {result.returncode}) gave no JSON report: {result.stderr[-2000:]}{result.stdout[:2000]}")


def objects_of_kinds(files: list[str]) -> collections.Counter:
    counts = collections.Counter()
    for name in files:
        with open(name, encoding="utf-8") as handle:
            counts.update(d["kind"] for d in yaml.safe_load_all(handle) if d and d.get("kind") in SCORED_KINDS)
    return counts


def describe(obj: dict) -> str:
    meta = obj["object_meta"]
    where = f"{meta['namespace']}/" if meta.get("namespace") else ""
    return f"{obj['type_meta']['kind']} {where}{meta['name']}"


def findings(report: list[dict], grade: int = CRITICAL) -> list[tuple[str, str, str]]:
    """(check id, object, what kube-score says) of every check not skipped at ``grade``."""
    found = []
    for obj in report:
        for check in obj["checks"]:
            if check["skipped"] or check["grade"] != grade:
                continue
            says = "; ".join(
                f"{c['path']}: {c['summary']}" if c["path"] else c["summary"] for c in check["comments"] or []
            )  # fmt: skip
            found.append((check["check"]["id"], describe(obj), says))
    return found


@pytest.fixture(scope="module")
def rendered(site, tmp_path_factory) -> dict[str, dict[str, list[str]]]:
    """Every example's manifest files by target cluster, rendered once for this module."""
    root = tmp_path_factory.mktemp("kube-score")
    return {path: render(path, site, str(root / example_id(path).replace("/", "-"))) for path in EXAMPLES}


def test_the_examples_are_found():
    assert len(TOP_LEVEL) >= 3, f"examples/*.yml found {len(TOP_LEVEL)} examples under {ROOT}"


def test_every_entry_says_why():
    for name, table in (("IGNORED", IGNORED), ("PENDING", PENDING), ("OPTIONS", OPTIONS), ("ASKED", ASKED)):
        for key, why in table.items():
            assert why.strip().endswith("."), f"{name}[{key!r}] needs its reason, in one sentence"
    assert not set(IGNORED) & set(PENDING)
    assert {example for example, _check, _obj in ASKED} <= {example_id(p) for p in EXAMPLES}


@pytest.mark.parametrize("path", EXAMPLES, ids=example_id)
def test_no_critical_finding(kube_score, rendered, path):
    problems = []
    for cluster, files in rendered[path].items():
        report = score(kube_score, files)
        where = f" in third-party cluster {cluster}" if cluster else ""
        scored = collections.Counter(o["type_meta"]["kind"] for o in report if o["type_meta"]["kind"] in SCORED_KINDS)
        assert scored == objects_of_kinds(files), f"kube-score did not score each object{where} once"
        problems += [
            f"{example_id(path)}{where}: {obj}: {check}: {says}"
            for check, obj, says in findings(report)
            if (example_id(path), check, obj) not in ASKED
        ]
    assert not problems, (
        f"kube-score's CRITICAL findings ({len(problems)}; fix the rendering, or add the check to IGNORED in "
        f"{os.path.relpath(__file__, ROOT)} with the reason it does not apply):\n" + "\n".join(problems)
    )


def test_ignored_checks_still_fire(kube_score, rendered):
    """Each entry of IGNORED, PENDING, OPTIONS and ASKED still hides a CRITICAL finding: one that hides nothing goes."""
    fired = collections.defaultdict(set)
    for path, by_cluster in rendered.items():
        for files in by_cluster.values():
            for check, obj, says in findings(score(kube_score, files, ignore=False)):
                fired[check].add(example_id(path))
                fired[example_id(path), check, obj].add(example_id(path))
                if check == "container-resources" and "CPU limit is not set" in says:
                    fired["--ignore-container-cpu-limit"].add(example_id(path))
    stale = [f"{name}[{check!r}]" for name, table in (("IGNORED", IGNORED), ("PENDING", PENDING), ("OPTIONS", OPTIONS))
             for check in table if not fired[check]]  # fmt: skip
    stale += [f"ASKED[{key!r}]" for key in ASKED if not fired[key]]
    assert not stale, f"no example fires these any more: remove them from {os.path.relpath(__file__, ROOT)}: {stale}"
