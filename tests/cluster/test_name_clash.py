"""Two deployments whose objects would get the same name, against the real local control plane.

Names join deployment, module and robot with '-': deployment ``a-b`` with module ``c`` and deployment ``a`` with
module ``b-c`` both name the instance of robot fetch-1 ``a-b-c-fetch-1``. The second deploy must stop before it
renders or writes anything, naming the module, the object and the deployment that owns it; the first deployment's
objects stay as they were. A negative control deploys a third spec whose names differ, to the same robot.
"""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.cluster

SPEC = """\
metadata:
  name: {deployment}
  targetFleet: test-fleet
  robotSelector:
    robot: [fetch-1]
rosModules:
- name: {module}
  image: registry.example/planner:1.0
  launch: ros2 run planner node
  rosParameters: {{planner: {{rate: 10}}}}
"""
NAMESPACE = "kuberos-test-fleet"


def write_spec(tmp_path, number, deployment, module):
    path = tmp_path / f"spec-{number}.yml"  # not named after deployment and module: those join alike here
    path.write_text(SPEC.format(deployment=deployment, module=module), encoding="utf-8")
    return path


def versions(cluster):
    core, apps, _ = cluster.clients()
    found = {}
    for item in apps.list_namespaced_deployment(NAMESPACE).items:
        found[("Deployment", item.metadata.name)] = item.metadata.resource_version
    for item in core.list_namespaced_config_map(NAMESPACE).items:
        found[("ConfigMap", item.metadata.name)] = item.metadata.resource_version
    return found


def test_a_second_deployment_cannot_take_the_names_of_the_first(cluster, tmp_path):
    first = write_spec(tmp_path, 1, "a-b", "c")
    second = write_spec(tmp_path, 2, "a", "b-c")
    third = write_spec(tmp_path, 3, "a", "d")
    try:
        done = cluster.deploy(first, tmp_path / "render-first")
        assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-2000:]
        before = versions(cluster)
        assert ("Deployment", "a-b-c-fetch-1") in before and ("ConfigMap", "a-b-c-params") in before

        clash = cluster.deploy(second, tmp_path / "render-second")
        output = clash.stdout + clash.stderr
        assert clash.returncode != 0, output[-6000:]
        assert "Traceback" not in output
        lines = [line.strip() for line in output.splitlines() if "rosModules[0].name: 'b-c' of deployment a would name" in line]
        assert lines, output[-6000:]
        assert any("Deployment a-b-c-fetch-1" in line and "belongs to deployment a-b (module c)" in line for line in lines), lines
        assert any(line.startswith(f"- {second}:7: rosModules[0].name: ") for line in lines), lines
        assert not (tmp_path / "render-second").exists() or not any((tmp_path / "render-second").iterdir())
        assert versions(cluster) == before  # nothing of the first was touched, nothing of the second was written

        # Negative control: another module name, same deployment name and robot, deploys.
        fine = cluster.deploy(third, tmp_path / "render-third")
        assert fine.returncode == 0, fine.stdout[-6000:] + fine.stderr[-2000:]
        assert ("Deployment", "a-d-fetch-1") in versions(cluster)
    finally:
        for spec in (third, first):
            cluster.undeploy(spec)
