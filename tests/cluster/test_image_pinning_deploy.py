"""playbooks/deploy.yml pins every image by digest (rosdeployment_pin_images), against the real local control plane
and a real registry (the CNCF distribution registry on loopback) that serves as the site's mirror of ghcr.io and
Docker Hub, as a site's nodes use one.

Proves: the rendered Deployments name image:tag@digest (the module's and the discovery servers'), the deployment
record keeps tag and digest; a tag that moves changes nothing in the cluster, and the next deploy's --check --diff
shows the image change before the deploy that applies it; a rollout resolves the tag again and rolls the new digest
out.
"""

from __future__ import annotations

import json
import os
import shutil

import pytest
from helpers import playbook
from oci import free_port, write_archive

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import registry as lab_registry

pytestmark = [
    pytest.mark.cluster,
    pytest.mark.skipif(
        not shutil.which("docker-registry") and not os.environ.get("CI"),
        reason="docker-registry is not installed (scripts/setup.sh installs it)",
    ),
]

SPEC = """metadata:
  name: pinned
  targetFleet: test-fleet
rosModules:
- name: talker
  image: ghcr.io/kuberos/pinned:1.0
  launch: ros2 run demo_nodes_cpp talker
  preference: edge
"""


@pytest.fixture
def mirror(tmp_path):
    running = lab_registry.LocalRegistry(str(tmp_path / "registry"), "127.0.0.1", free_port(), auth=False)
    try:
        assert running.start() is True
        yield running
    finally:
        running.stop(remove=True)


def images(apps, namespace: str) -> dict[str, str]:
    return {
        d.metadata.name: d.spec.template.spec.containers[0].image
        for d in apps.list_namespaced_deployment(namespace, label_selector="app.kubernetes.io/managed-by=kuberos").items
    }


def resource_versions(apps) -> dict[str, str]:
    return {d.metadata.name: d.metadata.resource_version for d in apps.list_namespaced_deployment("kuberos-test-fleet").items}


def test_a_deploy_pins_each_image_and_a_moved_tag_waits_for_the_next_deploy(cluster, mirror, tmp_path):
    core, apps, _discovery = cluster.clients()
    client = mirror.client()
    first = write_archive(str(tmp_path / "one.tar"), b"talker, first build\n")
    second = write_archive(str(tmp_path / "two.tar"), b"talker, second build\n")
    ros = write_archive(str(tmp_path / "ros.tar"), b"the discovery servers' image\n")
    client.push_archive(str(tmp_path / "one.tar"), "kuberos/pinned", "1.0")
    client.push_archive(str(tmp_path / "ros.tar"), "library/ros", "jazzy-ros-base")
    with open(mirror.ca_file, encoding="utf-8") as handle:
        entry = [{"url": f"https://{mirror.address}", "ca": handle.read()}]
    extra = json.dumps({"kuberos_pin_images": True, "rosdeployment_registry_mirrors": {"ghcr.io": entry, "docker.io": entry}})
    spec = tmp_path / "pinned.yml"
    spec.write_text(SPEC)
    try:
        deployed = cluster.deploy(spec, tmp_path / "render", "-e", extra)
        assert deployed.returncode == 0, deployed.stdout[-6000:]
        found = images(apps, "kuberos-test-fleet")
        talkers = {name: image for name, image in found.items() if name.startswith("pinned-talker-")}
        assert talkers and set(talkers.values()) == {f"ghcr.io/kuberos/pinned:1.0@{first}"}, found
        # the fleet's servers (others of the fleet's deployments, deployed by other tests unpinned, keep their own)
        servers = {image for name, image in found.items() if name.startswith("kuberos-discovery-")}
        assert servers == {f"ros:jazzy-ros-base@{ros}"}, found
        record = core.read_namespaced_config_map("kuberos-record-pinned", "kuberos-test-fleet")
        assert json.loads(record.data["options.json"])["image_digests"] == {
            "ghcr.io/kuberos/pinned:1.0": first, "ros:jazzy-ros-base": ros
        }  # fmt: skip
        versions = {
            d.metadata.name: d.metadata.resource_version for d in apps.list_namespaced_deployment("kuberos-test-fleet").items
        }

        client.push_archive(str(tmp_path / "two.tar"), "kuberos/pinned", "1.0")  # the tag moves
        assert images(apps, "kuberos-test-fleet") == found, "a moved tag changes nothing in the cluster"
        checked = cluster.deploy(spec, tmp_path / "render", "-e", extra, "--check", "--diff")
        assert checked.returncode == 0, checked.stdout[-6000:]
        assert second in checked.stdout and "image" in checked.stdout, checked.stdout[-6000:]
        after_check = {
            d.metadata.name: d.metadata.resource_version for d in apps.list_namespaced_deployment("kuberos-test-fleet").items
        }
        assert after_check == versions, "--check applies nothing"

        again = cluster.deploy(spec, tmp_path / "render", "-e", extra)
        assert again.returncode == 0, again.stdout[-6000:]
        moved = images(apps, "kuberos-test-fleet")
        assert {moved[name] for name in talkers} == {f"ghcr.io/kuberos/pinned:1.0@{second}"}
        assert {image for name, image in moved.items() if name.startswith("kuberos-discovery-")} == servers, "not moved"

        # a rollout resolves too: the tag moved again, and the rollout takes the module to the new digest in its waves
        third = write_archive(str(tmp_path / "three.tar"), b"talker, third build\n")
        client.push_archive(str(tmp_path / "three.tar"), "kuberos/pinned", "1.0")
        rolled = playbook(
            "rollout.yml", "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_kubeconfig={cluster.kubeconfig}",
            "-e", "rosdeployment_rollout_soak=1", "-e", "rosdeployment_rollout_prestage=false", "-e", extra,
        )  # fmt: skip
        assert rolled.returncode == 0, rolled.stdout[-6000:]
        assert {images(apps, "kuberos-test-fleet")[name] for name in talkers} == {f"ghcr.io/kuberos/pinned:1.0@{third}"}
        record = core.read_namespaced_config_map("kuberos-record-pinned", "kuberos-test-fleet")
        assert json.loads(record.data["options.json"])["image_digests"]["ghcr.io/kuberos/pinned:1.0"] == third
    finally:
        cluster.undeploy(spec)
