"""The robot pool against the real local control plane (kwok nodes), through the playbooks a developer runs.

alice reserves fetch-2 (playbooks/pool.yml, check mode first) and the playbook's pass (a rollout at the production
deployment's revision) stops what it ran there at once, while fetch-1's objects and the fleet's discovery servers are
not touched (same resourceVersions); the deployment's next deploy and a rollout leave fetch-2 out too; alice's
development deployment runs on fetch-2, bob's is refused, and bob cannot take or release alice's robot; alice gives
fetch-2 back and the pass returns the production deployment to it at once (its current revision), fetch-1 still
untouched; its next deploy changes nothing.
"""

from __future__ import annotations

import re

import pytest
from helpers import playbook

pytestmark = pytest.mark.cluster

PRODUCTION = """\
apiVersion: kuberos.io/v1alpha1
kind: RosDeployment
metadata: {name: pool-app, targetFleet: test-fleet}
rosModules:
- name: driver
  image: reg/driver:1
  launch: drive
  requirements: {onboard: true}
  resources: {cpu: 50m, memory: 64Mi}
- name: planner
  image: reg/planner:1
  launch: plan
  preference: edge
  resources: {cpu: 50m, memory: 64Mi}
"""
DEVELOPMENT = PRODUCTION.replace(
    "metadata: {name: pool-app, targetFleet: test-fleet}",
    "metadata: {name: pool-dev, targetFleet: test-fleet, developer: DEV, robotSelector: {robot: [fetch-2]}}",
)


def said(result) -> str:
    """The play's output with its line wrapping undone (the callback folds long messages)."""
    return " ".join(result.stdout.split())


def _versions(apps, core, namespace, names):
    objects = [*apps.list_namespaced_deployment(namespace).items, *core.list_namespaced_service(namespace).items]
    return {
        (o.kind or type(o).__name__, o.metadata.name): o.metadata.resource_version for o in objects if o.metadata.name in names
    }


def test_a_reserved_robot_is_left_out_of_production_given_to_its_developer_and_given_back(cluster, tmp_path):
    core, apps, _ = cluster.clients()
    namespace = "kuberos-test-fleet"
    production, development = tmp_path / "pool-app.yml", tmp_path / "pool-dev.yml"
    production.write_text(PRODUCTION, encoding="utf-8")

    def pool(*extra):
        return playbook("pool.yml", "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", "-e", "rosdeployment_rollout_soak=1",
                        *extra, timeout=600)  # fmt: skip

    def instances(deployment):
        found = apps.list_namespaced_deployment(namespace, label_selector=f"kuberos.io/deployment={deployment}").items
        return sorted(d.metadata.name for d in found if d.metadata.labels.get("kuberos.io/component") == "ros-module")

    first = cluster.deploy(production, tmp_path / "render")
    assert first.returncode == 0, first.stdout[-5000:]
    assert instances("pool-app") == ["pool-app-driver-fetch-1", "pool-app-driver-fetch-2", "pool-app-planner-fetch-1",
                                     "pool-app-planner-fetch-2"]  # fmt: skip
    untouched = ["pool-app-driver-fetch-1", "pool-app-planner-fetch-1", "kuberos-robot-discovery-pool-app-fetch-1",
                 "kuberos-discovery-0", "kuberos-discovery-1"]  # fmt: skip
    before = _versions(apps, core, namespace, untouched)
    assert sorted({name for _kind, name in before}) == sorted(untouched) and len(before) == 7, before
    try:
        alice = ("-e", "robot=fetch-2", "-e", "owner=alice", "-e", '{"reason": "grasp tests"}', "-e", "hold=2h")
        named = pool("-e", "robot=fetch-2", "-e", '{"owner": "Alice Smith"}')
        assert named.returncode != 0, named.stdout[-3000:]
        assert "owner: 'Alice Smith' cannot be a RosDeployment's metadata.developer" in said(named), named.stdout[-3000:]
        assert core.list_namespaced_config_map(namespace, label_selector="kuberos.io/reservation=true").items == []
        checked = pool(*alice, "--check", "--diff")
        assert checked.returncode == 0 and checked.changed == 1, checked.stdout[-3000:]
        assert "+owner: alice" in checked.stdout and "no robot is reserved" in checked.stdout, checked.stdout[-3000:]
        assert re.search(r"would stop what (\S+, )*pool-app(, \S+)* run\(s\) for fetch-2 at once", said(checked)), checked.stdout
        reserved = pool(*alice)
        assert reserved.returncode == 0 and reserved.changed >= 2, reserved.stdout[-3000:]  # the reservation, the pass
        assert "fetch-2 (fleet test-fleet) is reserved by alice until" in said(reserved), reserved.stdout[-3000:]
        # Other tests on the shared cluster may leave their own deployments on fetch-2: pool-app is one of the list.
        still = re.search(r"still running for production: ([^()]+) \(their next pass stops it there\)", said(reserved))
        assert still and "pool-app" in still.group(1).split(", "), reserved.stdout[-3000:]
        # ... and the playbook runs that pass at once: a rollout at pool-app's revision stops fetch-2's modules.
        assert "pool-app: revision 1 -> 1" in said(reserved), reserved.stdout[-4000:]
        assert "Deployment/pool-app-driver-fetch-2: remove (no longer rendered)" in said(reserved), reserved.stdout[-4000:]
        assert "left out, reserved in the robot pool: fetch-2 (reserved by alice until" in said(reserved)
        assert instances("pool-app") == ["pool-app-driver-fetch-1", "pool-app-planner-fetch-1"]
        assert _versions(apps, core, namespace, untouched) == before, "fetch-1 and the fleet's servers did not move"
        assert "fetch-2 (test-fleet): alice until" in said(reserved), reserved.stdout[-3000:]
        assert ": grasp tests" in said(reserved), reserved.stdout[-3000:]
        again = pool(*alice)
        assert again.returncode == 0, again.stdout[-3000:]
        assert "revision 1 -> 1" not in said(again), "nothing of production runs there any more: no pass"
        taken = pool("-e", "robot=fetch-2", "-e", "owner=bob")
        assert taken.returncode != 0 and "robot fetch-2 is reserved by alice until" in said(taken), taken.stdout[-3000:]
        assert "ask alice to release it, or wait" in said(taken)

        # The deployment's next deploy leaves fetch-2 out too, and changes nothing.
        left = cluster.deploy(production, tmp_path / "render")
        assert left.returncode == 0, left.stdout[-5000:]
        assert "pool-app leaves out 1 reserved robot(s): fetch-2 (reserved by alice until" in said(left), left.stdout[-4000:]
        assert instances("pool-app") == ["pool-app-driver-fetch-1", "pool-app-planner-fetch-1"]
        assert _versions(apps, core, namespace, untouched) == before, "fetch-1 and the fleet's servers did not move"

        # A rollout of a new planner leaves the reserved robot out too: fetch-1's planner alone is upgraded.
        production.write_text(PRODUCTION.replace("reg/planner:1", "reg/planner:2"), encoding="utf-8")
        rolled = playbook("rollout.yml", "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", "-e",
                          f"rosdeployment_file={production}", "-e", "rosdeployment_rollout_soak=1", timeout=600)  # fmt: skip
        assert rolled.returncode == 0, rolled.stdout[-5000:]
        assert "left out, reserved in the robot pool: fetch-2 (reserved by alice until" in said(rolled), rolled.stdout[-4000:]
        images = {
            d.metadata.name: d.spec.template.spec.containers[0].image for d in apps.list_namespaced_deployment(namespace).items
        }
        assert images["pool-app-planner-fetch-1"].startswith("reg/planner:2") and "pool-app-planner-fetch-2" not in images
        before = _versions(apps, core, namespace, untouched)

        development.write_text(DEVELOPMENT.replace("DEV", "bob"), encoding="utf-8")
        refused = cluster.deploy(development, tmp_path / "render-dev")
        assert refused.returncode != 0
        assert "robot fetch-2 is reserved by alice until" in said(refused), refused.stdout[-4000:]
        assert "the development deployment of bob runs only on robots bob holds" in said(refused)
        assert instances("pool-dev") == [], "nothing applied"
        development.write_text(DEVELOPMENT.replace("DEV", "alice"), encoding="utf-8")
        dev = cluster.deploy(development, tmp_path / "render-dev")
        assert dev.returncode == 0, dev.stdout[-5000:]
        assert instances("pool-dev") == ["pool-dev-driver-fetch-2", "pool-dev-planner-fetch-2"]
        assert _versions(apps, core, namespace, untouched) == before

        stolen = pool("-e", "robot=fetch-2", "-e", "owner=bob", "-e", "state=absent")
        assert stolen.returncode != 0 and "only alice releases it (or force: true)" in said(stolen), stolen.stdout[-3000:]
        assert cluster.undeploy(development).returncode == 0
        released = pool("-e", "robot=fetch-2", "-e", "owner=alice", "-e", "state=absent")
        assert released.returncode == 0 and released.changed >= 2, released.stdout[-3000:]  # the release, the pass
        assert "the fleet's deployments return to it on their next pass" in said(released)
        assert "no robot is reserved" in released.stdout
        # The pass at once: pool-app (at its revision 2, the new planner) returns to fetch-2; fetch-1 is untouched.
        assert "pool-app: revision 2 -> 2" in said(released), released.stdout[-4000:]
        assert "fetch-2: driver: create (new); planner: create (new)" in said(released), released.stdout[-4000:]
        assert instances("pool-app") == ["pool-app-driver-fetch-1", "pool-app-driver-fetch-2", "pool-app-planner-fetch-1",
                                         "pool-app-planner-fetch-2"]  # fmt: skip
        image = apps.read_namespaced_deployment("pool-app-planner-fetch-2", namespace).spec.template.spec.containers[0].image
        assert image.startswith("reg/planner:2"), image
        assert _versions(apps, core, namespace, untouched) == before, "given back: fetch-1 still untouched"

        back = cluster.deploy(production, tmp_path / "render")
        assert back.returncode == 0, back.stdout[-5000:]
        assert "leaves out" not in back.stdout
        assert instances("pool-app") == ["pool-app-driver-fetch-1", "pool-app-driver-fetch-2", "pool-app-planner-fetch-1",
                                         "pool-app-planner-fetch-2"]  # fmt: skip
        assert _versions(apps, core, namespace, untouched) == before, "given back: fetch-1 still untouched"
    finally:
        pool("-e", "robot=fetch-2", "-e", "owner=alice", "-e", "state=absent", "-e", "force=true")
        if development.exists():
            cluster.undeploy(development)
        cluster.undeploy(production)
