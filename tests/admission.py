"""The pods the collection renders, and the API server's own Pod Security admission asked about them.

``example_pods`` renders every example as deploy renders it on the embedded site (inventories/local with its software
catalog; partner-cloud with the third-party cluster it names) and returns each pod template; ``opt_out_pods`` adds the
modules that ask for more (``user: 0``, ``privileged: true``). ``verdicts`` dry-run creates each as a Pod in three
namespaces of a real API server, one enforcing each level, and returns what the server said: the cluster tests hold
``pod_security.level`` to it, and bench/bench_pod_security.py counts it.
"""

from __future__ import annotations

import copy
import glob
import os

from helpers import ROOT, inventory_raw

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import batch, pod_security
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    RenderOptions,
    render_deployment,
    render_remote,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployment_file, parse_rosdeployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import controller_objects

EXAMPLES = sorted(
    os.path.relpath(p, ROOT)
    for p in glob.glob(os.path.join(ROOT, "examples", "*.yml"))
    if not p.endswith("-catalog.yml")  # a software catalog, not a deployment (rendered through pick-and-place)
)
# the reference format's ApplicationDeployment renders as a RosDeployment does
EXAMPLES += ["examples/reference/talker-listener.kuberos.yml"]
BATCH_EXAMPLES = sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, "examples", "batch", "*.yml")))
BATCH_EXAMPLES += ["examples/reference/grid.batchjob.yml"]
# The pods of the examples that ask for more than restricted, and the level each needs: the declared opt-outs.
DECLARED = {
    # its talker drives a gripper (a host device): the reference format's requirements.privilege
    ("examples/reference/talker-listener.kuberos.yml", "Deployment/talker-listener-talker-fetch-1"): "privileged",
}
# examples/partner-cloud.yml places its planner in a third-party cluster the inventory must register
PARTNER = {"kuberos_latency_ms": 30, "kuberos_fleets": ["test-fleet"], "kuberos_bridge_endpoint": "203.0.113.10"}


def site_inventory(path: str = ""):
    raw = copy.deepcopy(inventory_raw())
    if path.endswith("partner-cloud.yml"):
        raw["hosts"]["partner-cloud"] = dict(PARTNER)
        raw["groups"]["clusters"] = ["partner-cloud"]
    return load_inventory(raw)


def render_example(path: str) -> list[dict]:
    """Every object deploy renders for the example at ``path`` (this cluster's, then each third-party cluster's)."""
    inventory = site_inventory(path)
    catalog = load_catalog(os.path.join(ROOT, "inventories", "local", "catalog"))
    deployments = load_rosdeployment_file(os.path.join(ROOT, path), path, catalog=catalog)
    placement = place_modules(deployments, inventory)
    objects = render_deployment(deployments, placement, RenderOptions())
    for remote in render_remote(deployments, placement, inventory.clusters, RenderOptions()).values():
        objects += remote
    return objects


def render_batch_example(path: str) -> list[dict]:
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import batch_runner

    inventory = site_inventory(path)
    with open(os.path.join(ROOT, path), encoding="utf-8") as handle:
        job = batch.with_fleet(batch.load_batch_jobs(handle.read(), path)[0], list(inventory.fleets))
    return batch.render_batch(job, batch_runner.place(job, inventory), RenderOptions())


def pods_of(objects: list[dict]) -> list[tuple[str, dict]]:
    """(Kind/name, pod spec) of every object that makes pods."""
    return [(f"{o['kind']}/{o['metadata']['name']}", spec) for o in objects if (spec := pod_security.pod_spec_of(o)) is not None]


def example_pods() -> dict[str, list[tuple[str, dict]]]:
    """Per example (and the controller), the pods it renders."""
    found = {path: pods_of(render_example(path)) for path in EXAMPLES}
    found.update({path: pods_of(render_batch_example(path)) for path in BATCH_EXAMPLES})
    found["controller (roles/controller)"] = pods_of(
        controller_objects("kuberos-system", "ghcr.io/kuberos/controller:0.2.0", ["test-fleet"], [], tls_secret="tls")
    )
    return found


def opt_out_pods() -> list[tuple[str, dict]]:
    """The pods of modules that ask for more than restricted: root (``user: 0``), privileged, both."""
    found = []
    for fields in ({"user": 0}, {"privileged": True}, {"privileged": True, "user": 1000}):
        spec = {
            "metadata": {"name": "asks", "targetFleet": "test-fleet"},
            "rosModules": [{"name": "driver", "image": "ros:jazzy-ros-base", "launch": "ros2 run x y", **fields,
                            "requirements": {"onboard": True}}],
        }  # fmt: skip
        dep = parse_rosdeployment(spec, "asks.yml")
        objects = render_deployment([dep], place_modules([dep], site_inventory()), RenderOptions())
        found += [(f"{name} ({fields})", pod) for name, pod in pods_of(objects) if "-driver-" in name][:1]
    return found


def level_namespaces(core, prefix: str = "kuberos-pss") -> dict[str, str]:
    """One namespace per Pod Security level, each enforcing it (created, or relabelled when it exists)."""
    from kubernetes.client.exceptions import ApiException

    names = {}
    for level in pod_security.LEVELS:
        name = f"{prefix}-{level}"
        body = {"metadata": {"name": name, "labels": {pod_security.ENFORCE: level, pod_security.ENFORCE_VERSION: "latest"}}}
        try:
            core.create_namespace(body)
        except ApiException as exc:
            if exc.status != 409:
                raise
            core.patch_namespace(name, body)
        names[level] = name
    return names


def verdicts(core, pods: list[tuple[str, dict]], namespaces: dict[str, str]) -> dict[tuple[str, str], str]:
    """(pod, level) -> "" when the API server admits the pod (a dry-run create) where ``level`` is enforced, else its
    reason."""
    from kubernetes.client.exceptions import ApiException

    out = {}
    for index, (name, spec) in enumerate(pods):
        body = {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": f"probe-{index}"}, "spec": copy.deepcopy(spec)}
        body["spec"].pop("serviceAccountName", None)  # its account lives in its own namespace; no matter to the level
        for level, namespace in namespaces.items():
            try:
                core.create_namespaced_pod(namespace, body, dry_run="All")
                out[(name, level)] = ""
            except ApiException as exc:
                if exc.status != 403 or "PodSecurity" not in (exc.body or ""):
                    raise
                out[(name, level)] = exc.body
    return out


def admitted_counts(pods: list[tuple[str, dict]], found: dict[tuple[str, str], str]) -> dict[str, int]:
    return {level: sum(1 for name, _spec in pods if found[(name, level)] == "") for level in pod_security.LEVELS}
