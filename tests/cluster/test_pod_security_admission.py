"""The API server's own Pod Security admission (the real kube-apiserver of the local control plane) on every pod the
collection renders: every example's pods are admitted where ``restricted`` is enforced, the modules that ask for more
only where their level is, and the collection's own reading of the standard (``pod_security.level``, which decides
what a fleet namespace enforces) agrees with the server on every pod at every level. A deploy labels the fleet's
namespace so that the cluster enforces it.
"""

from __future__ import annotations

import os

import pytest
from admission import DECLARED, example_pods, level_namespaces, opt_out_pods, verdicts
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pod_security

pytestmark = pytest.mark.cluster


@pytest.fixture(scope="module")
def namespaces(cluster):
    core, _apps, _discovery = cluster.clients()
    return core, level_namespaces(core)


def test_every_rendered_pod_is_admitted_under_restricted_by_the_api_server_but_the_declared_opt_outs(namespaces):
    core, by_level = namespaces
    found = example_pods()
    pods = [(f"{path}: {name}", spec) for path, per_example in found.items() for name, spec in per_example]
    assert len(found) >= 9 and len(pods) >= 30, {k: len(v) for k, v in found.items()}
    said = verdicts(core, pods, by_level)
    declared = {f"{path}: {name}": level for (path, name), level in DECLARED.items()}
    for name, _spec in pods:
        level = declared.get(name, "restricted")  # restricted, or the level the example declares (and no stricter)
        assert said[(name, level)] == "", (name, level, said[(name, level)][:400])
        stricter = pod_security.LEVELS[: pod_security.LEVELS.index(level)]
        assert all(said[(name, other)] for other in stricter), (name, level)


def test_the_collections_reading_of_the_standard_is_the_api_servers_at_every_level(namespaces):
    core, by_level = namespaces
    pods = opt_out_pods() + [
        (f"{path}: {name}", spec) for path, per_example in example_pods().items() for name, spec in per_example[:2]
    ]
    said = verdicts(core, pods, by_level)
    for name, spec in pods:
        needed, why = pod_security.level(spec)
        for level in pod_security.LEVELS:
            admitted = pod_security.LEVELS.index(level) >= pod_security.LEVELS.index(needed)
            assert (said[(name, level)] == "") == admitted, (name, level, needed, why, said[(name, level)][:400])
    levels = {name.split(" (")[1]: pod_security.level(spec)[0] for name, spec in opt_out_pods()}
    assert levels == {"{'user': 0})": "baseline", "{'privileged': True})": "privileged",
                      "{'privileged': True, 'user': 1000})": "privileged"}  # fmt: skip


def test_a_deploy_makes_the_cluster_enforce_the_level_of_the_fleets_pods(cluster, tmp_path):
    core, _apps, _discovery = cluster.clients()
    result = cluster.deploy(os.path.join(ROOT, "examples", "two-fleets.yml"), tmp_path / "render")
    assert result.returncode == 0, result.stdout[-6000:]
    try:
        for namespace in ("kuberos-test-fleet", "kuberos-warehouse-fleet"):
            labels = core.read_namespace(namespace).metadata.labels
            assert labels[pod_security.ENFORCE] == "restricted" and labels[pod_security.WARN] == "restricted", labels
            pods = core.list_namespaced_pod(namespace, label_selector="app.kubernetes.io/managed-by=kuberos").items
            assert pods and all(p.spec.security_context.seccomp_profile.type == "RuntimeDefault" for p in pods)
    finally:
        cluster.undeploy(os.path.join(ROOT, "examples", "two-fleets.yml"))
