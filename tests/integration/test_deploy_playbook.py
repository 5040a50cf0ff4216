"""playbooks/deploy.yml end to end with ansible-playbook, against the embedded local inventory.

Each behaviour is run twice where it matters (changed, then not changed), and check mode and
diff are separate cases. Nothing here needs a cluster: kuberos_apply is false (tests/cluster applies).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess

import pytest
from helpers import ROOT, venv_tool, without_module

pytestmark = pytest.mark.playbook


def deploy(spec, render_dir, *extra, inventory="inventories/local"):
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1", "ANSIBLE_FORCE_COLOR": "0"}
    command = [
        venv_tool("ansible-playbook"),
        "playbooks/deploy.yml",
        "-i",
        str(inventory),
        "-e",
        f"rosdeployment_file={spec}",
        "-e",
        f"kuberos_render_dir={render_dir}",
        "-e",
        "kuberos_apply=false",
        *extra,
    ]
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    recap = re.search(r"localhost\s+: ok=(\d+)\s+changed=(\d+)\s+unreachable=\d+\s+failed=(\d+)", result.stdout)
    result.changed = int(recap.group(2)) if recap else None
    return result


def manifests(render_dir):
    found = []
    for dirpath, _dirs, names in os.walk(os.path.join(render_dir, "manifests")):
        found.extend(os.path.relpath(os.path.join(dirpath, n), render_dir) for n in names)
    return sorted(found)


def test_listing_1_renders_then_changes_nothing(tmp_path):
    out = tmp_path / "render"
    first = deploy("examples/listing1.yml", out)
    assert first.returncode == 0, first.stdout + first.stderr
    assert first.changed == 1
    placement = json.loads((out / "placement.json").read_text())
    rows = {(p["robot"], p["module"]): (p["node"], p["tier"]) for p in placement["placements"]}
    assert rows == {
        ("fetch-1", "fetch-controller-foxy"): ("fetch-1", "onboard"),
        ("fetch-2", "fetch-controller-foxy"): ("fetch-2", "onboard"),
        ("fetch-1", "fetch-motion-planner"): ("cloud-1", "cloud"),
        ("fetch-2", "fetch-motion-planner"): ("cloud-2", "cloud"),
    }
    assert all(p["reason"] for p in placement["placements"])
    # The table is printed at the end of the run.
    assert re.search(r"kubeross-demo-picking\s+fetch-1\s+fetch-motion-planner\s+cloud\s+cloud-1", first.stdout)
    # Namespace, 2 discovery Services and Deployments, 4 module Deployments, the robots' own discovery servers (a
    # Deployment on each robot and their Service), the deployment record ConfigMap, its revision 1 and the site's
    # software catalog (inventories/local/catalog).
    assert len(manifests(out)) == 17  # with the fleet's two NetworkPolicies
    second = deploy("examples/listing1.yml", out)
    assert second.returncode == 0 and second.changed == 0, second.stdout


def test_check_mode_writes_nothing_and_reports_change(tmp_path):
    out = tmp_path / "render"
    result = deploy("examples/pick-and-place.yml", out, "--check")
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.changed == 1
    assert not out.exists()


def test_diff_shows_what_an_edit_changes_and_prune_removes_dropped_modules(tmp_path):
    out = tmp_path / "render"
    spec = tmp_path / "app.yml"
    shutil.copy(os.path.join(ROOT, "examples", "pick-and-place.yml"), spec)
    assert deploy(spec, out).returncode == 0
    before = manifests(out)
    text = spec.read_text().replace("planning_time: 2.0", "planning_time: 5.0")
    spec.write_text(text)
    checked = deploy(spec, out, "--check", "--diff")
    assert checked.returncode == 0 and checked.changed == 1
    assert re.search(r"^-\s+planning_time: 2.0$", checked.stdout, re.M), checked.stdout
    assert re.search(r"^\+\s+planning_time: 5.0$", checked.stdout, re.M), checked.stdout
    assert (
        "planning_time: 2.0"
        in (out / "manifests/kuberos-test-fleet/configmap-pick-and-place-motion-planner-params.yaml").read_text()
    )
    # Drop the task coordinator: its Deployment file goes, the rest stays.
    spec.write_text(without_module(text, "task-coordinator"))
    applied = deploy(spec, out)
    assert applied.returncode == 0 and applied.changed == 1
    after = manifests(out)
    gone = sorted(set(before) - set(after))
    assert gone == ["manifests/kuberos-test-fleet/deployment-pick-and-place-task-coordinator-shared-0.yaml"]
    assert deploy(spec, out).changed == 0


def test_two_fleets_get_their_own_namespaces(tmp_path):
    out = tmp_path / "render"
    result = deploy("examples/two-fleets.yml", out)
    assert result.returncode == 0, result.stdout + result.stderr
    namespaces = {path.split("/")[1] for path in manifests(out) if not path.startswith("manifests/_cluster")}
    assert namespaces == {"kuberos-test-fleet", "kuberos-warehouse-fleet"}


BAD = {
    "unknown-field": (
        "metadata: {name: demo, targetFleet: test-fleet}\nrosModules:\n"
        "- name: planner\n  image: x\n  launch: [run]\n  prefrence: cloud\n",
        [r"app.yml:6: rosModules\[0\].prefrence: unknown field; did you mean 'preference'\?"],
    ),
    "unknown-fleet": (
        "metadata: {name: demo, targetFleet: test-flet}\nrosModules:\n- {name: planner, image: x, launch: run}\n",
        [r"app.yml:1: metadata.targetFleet: 'test-flet' is not a fleet in the inventory; did you mean 'test-fleet'\?"],
    ),
    "infeasible": (
        "metadata: {name: demo, targetFleet: test-fleet}\nrosModules:\n"
        "- {name: planner, image: x, launch: run, preference: cloud, requirements: {max_latency: 10 ms}, resources: {gpu: 4}}\n",
        [
            r"has no feasible node for robot fetch-1",
            r"cloud-1 \(cloud\): latency 40 ms to fetch-1 > max_latency 10 ms",
            r"edge-1 \(edge\): gpu: needs 4, node has none",
        ],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_fails_clearly_and_writes_nothing(tmp_path, case):
    text, patterns = BAD[case]
    spec = tmp_path / "app.yml"
    spec.write_text(text)
    out = tmp_path / "render"
    result = deploy(spec, out)
    assert result.returncode != 0
    for pattern in patterns:
        assert re.search(pattern, result.stdout), result.stdout
    assert "Traceback" not in result.stdout + result.stderr
    assert not out.exists()


def test_refuses_to_render_into_a_foreign_directory(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    result = deploy("examples/listing1.yml", out)
    assert result.returncode != 0
    assert "was not written by KubeROS" in result.stdout
    assert sorted(os.listdir(out)) == ["notes.txt"]


def test_missing_spec_file_is_named(tmp_path):
    result = deploy(tmp_path / "nope.yml", tmp_path / "render")
    assert result.returncode != 0
    assert "nope.yml: cannot read the file: No such file or directory" in result.stdout


def test_bad_inventory_names_host_and_variable(tmp_path):
    inventory = tmp_path / "hosts.yml"
    inventory.write_text(
        "all:\n  children:\n    robots:\n      hosts:\n"
        "        fetch-1: {kuberos_fleet: test-fleet, kuberos_cpu: four, kuberos_memory: 8Gi}\n"
        "        fetch-2: {kuberos_cpu: 2, kuberos_memory: 8Gi}\n"
    )
    result = deploy("examples/listing1.yml", tmp_path / "render", inventory=inventory)
    assert result.returncode != 0
    assert "hosts.fetch-1.kuberos_cpu: 'four' is not valid; expected a CPU quantity" in result.stdout
    assert "hosts.fetch-2.kuberos_fleet: is required for a robot" in result.stdout
    assert "Traceback" not in result.stdout + result.stderr
    assert not (tmp_path / "render").exists()


@pytest.mark.parametrize("playbook", ["deploy.yml", "undeploy.yml", "rollout.yml"])
def test_a_failing_spec_is_reported_once_by_the_first_task_that_reads_it(tmp_path, playbook):
    spec = tmp_path / "app.yml"
    spec.write_text(
        "metadata: {name: Bad_Name, targetFleet: test-fleet}\nrosModules:\n- name: planner\n  image: x\n  launch: [run]\n"
        "  prefrence: cloud\n"
    )
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1", "ANSIBLE_FORCE_COLOR": "0"}
    command = [
        venv_tool("ansible-playbook"), f"playbooks/{playbook}", "-i", "inventories/local", "-e", f"rosdeployment_file={spec}",
        "-e", f"kuberos_render_dir={tmp_path / 'render'}", "-e", f"kuberos_kubeconfig={tmp_path / 'no-cluster'}",
    ]  # fmt: skip
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    assert result.returncode != 0
    for problem in (
        "app.yml:1: metadata.name: 'Bad_Name' is not valid",
        "app.yml:6: rosModules[0].prefrence: unknown field; did you mean 'preference'?",
    ):
        assert output.count(problem) == 1, output
    failed = re.findall(r"^TASK \[(?:kuberos\.platform\.rosdeployment : )?([^\]]+)\]", output.split("fatal:")[0], re.M)
    first_task = {
        "deploy.yml": "Validate, place, render, dry-run, apply, prune and wait",  # one module reads the spec first
        "undeploy.yml": "Remove every object of the deployment",
        "rollout.yml": "Validate the RosDeployment",
    }
    assert failed[-1] == first_task[playbook], output
    assert "caused by" not in output and "Traceback" not in output
    assert not (tmp_path / "render").exists()
