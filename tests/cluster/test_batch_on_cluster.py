"""Batch jobs on the real local control plane: playbooks/batch.yml runs every combination of a grid as indexed Jobs,
wave after wave, on the nodes the scheduler chose, and collects every run; a second run replaces the first; a run
that cannot start is stopped at its start-up timeout; state absent removes the job.

The nodes are kwok's: the Job controller creates the pods, kube-scheduler binds them to the placed node and kwok
completes them (its pod-complete stage), so what runs here is Kubernetes' own Job machinery, not the modules'
programs; a module's exit code, logs and the running timeout need a kubelet (the outcome of a pod's status is unit
tested in tests/unit/test_batch.py).
"""

from __future__ import annotations

import csv
import json
import os

import pytest
from helpers import ROOT, playbook

pytestmark = pytest.mark.cluster

NAMESPACE = "kuberos-test-fleet"
NAV = os.path.join(ROOT, "examples", "batch", "nav-grid.yml")
STUCK = """\
kind: RosBatchJob
metadata: {name: stuck, targetFleet: test-fleet, robotSelector: {robot: [fetch-1]}}
job: {module: trial, repeat: 2, startupTimeout: 3 s, grid: [{map: p, key: speed, values: [1]}]}
parameterMaps: [{name: p, type: key-value, data: {speed: 1}}]
rosModules: [{name: trial, image: example/trial:1, launch: run, preference: [edge], launchArguments: {speed: "{p.speed}"}}]
"""


def run(cluster, spec, render_dir, *extra):
    return playbook(
        "batch.yml", "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={render_dir}",
        "-e", f"kuberos_kubeconfig={cluster.kubeconfig}", *extra, timeout=600,
    )  # fmt: skip


def batch_api(cluster):
    from kubernetes import client, config

    return client.BatchV1Api(config.new_client_from_config(config_file=cluster.kubeconfig))


def jobs_of(cluster, name):
    return {
        j.metadata.name: j
        for j in batch_api(cluster).list_namespaced_job(NAMESPACE, label_selector=f"kuberos.io/batch={name}").items
    }


def test_the_grid_runs_in_waves_on_the_placed_nodes_and_is_collected(cluster, tmp_path):
    out = tmp_path / "nav"
    first = run(cluster, NAV, out)
    assert first.returncode == 0, first.stdout[-5000:] + first.stderr[-2000:]
    assert "8 of 8 runs succeeded" in first.stdout
    jobs = jobs_of(cluster, "nav-grid")
    assert sorted(jobs) == ["nav-grid-0", "nav-grid-1", "nav-grid-2", "nav-grid-3"]
    for job in jobs.values():
        assert job.status.succeeded == 2 and job.status.completed_indexes == "0,1", job.status
    # wave 2 (combinations 2 and 3) started after wave 1 had finished
    wave_one_done = max(jobs[n].status.completion_time for n in ("nav-grid-0", "nav-grid-1"))
    assert min(jobs[n].metadata.creation_timestamp for n in ("nav-grid-2", "nav-grid-3")) >= wave_one_done.replace(microsecond=0)
    core, _apps, _discovery = cluster.clients()
    pods = core.list_namespaced_pod(NAMESPACE, label_selector="kuberos.io/batch=nav-grid").items
    assert len(pods) == 8
    for pod in pods:  # every run on the node its combination's slot was placed on
        assert pod.spec.node_name == jobs[pod.metadata.labels["job-name"]].metadata.annotations["kuberos.io/node"]
    with open(out / "results.csv", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 8 and {r["state"] for r in rows} == {"succeeded"}
    assert {json.loads(r["parameters"])["scenario.world"] for r in rows} == {"maze", "warehouse"}
    assert sorted(os.listdir(out / "runs")) == [f"{n}-{k}" for n in range(4) for k in range(2)]
    result = json.loads((out / "runs" / "3-1" / "result.json").read_text())
    assert result["parameters"] == {"scenario.planner": "PRM", "scenario.world": "warehouse"} and result["state"] == "succeeded"
    progress = (out / "progress.log").read_text()
    assert "wave 1/2: starting runs 0, 1" in progress and "wave 2/2: 8 of 8 runs done (8 succeeded, 0 failed)" in progress

    # a second run replaces the first's Jobs; state absent removes the job
    uids = {name: job.metadata.uid for name, job in jobs.items()}
    second = run(cluster, NAV, out)
    assert second.returncode == 0, second.stdout[-3000:]
    again = jobs_of(cluster, "nav-grid")
    assert sorted(again) == sorted(uids) and all(again[n].metadata.uid != uids[n] for n in uids)
    removed = run(cluster, NAV, out, "-e", "rosdeployment_batch_state=absent")
    assert removed.returncode == 0, removed.stdout[-3000:]
    assert not jobs_of(cluster, "nav-grid")
    assert not core.list_namespaced_config_map(NAMESPACE, label_selector="kuberos.io/batch=nav-grid").items


def test_a_run_that_cannot_start_fails_at_its_startup_timeout(cluster, tmp_path):
    spec = tmp_path / "stuck.yml"
    spec.write_text(STUCK, encoding="utf-8")
    core, _apps, _discovery = cluster.clients()
    cordoned = ["edge-1", "edge-2", "edge-3"]
    try:
        for node in cordoned:  # Ready (so placed there) but unschedulable: the run's pod stays Pending
            core.patch_node(node, {"spec": {"unschedulable": True}})
        result = run(cluster, spec, tmp_path / "stuck")
    finally:
        for node in cordoned:
            core.patch_node(node, {"spec": {"unschedulable": False}})
    assert result.returncode == 0, result.stdout[-4000:]
    assert "0 of 2 runs succeeded" in result.stdout
    runs = json.loads((tmp_path / "stuck" / "results.json").read_text())
    assert [(r["repeat"], r["state"]) for r in runs] == [(0, "failed"), (1, "failed")]
    assert all(r["why"] == "startup timeout: not started within 3 s" for r in runs)
    run(cluster, spec, tmp_path / "stuck", "-e", "rosdeployment_batch_state=absent")
