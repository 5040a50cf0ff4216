"""Batch jobs (kuberos/batch.py, batch_runner.py): the grid, waves, placement, the rendered Jobs, the reference
format's BatchJob, errors, and how a pod's status becomes a run's outcome. Every rendered object is checked against
the Kubernetes 1.34 schema. Running them on a cluster: tests/cluster/test_batch_on_cluster.py."""

from __future__ import annotations

import json
import os

import kubernetes_validate
import pytest
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import batch
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import file_reader
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import batch_runner

NAV = os.path.join(ROOT, "examples", "batch", "nav-grid.yml")
GRASP = os.path.join(ROOT, "examples", "reference", "grid.batchjob.yml")


def load(path):
    (job,) = batch.load_batch_jobs(open(path, encoding="utf-8").read(), path, read_file=file_reader(path))
    return job


def problems_of(text: str) -> list[str]:
    with pytest.raises(SpecError) as caught:
        batch.load_batch_jobs(text, "job.yml")
    return [str(p) for p in caught.value.problems]


def test_the_grid_runs_every_combination_in_waves(local_inventory):
    job = load(NAV)
    assert len(job.combinations()) == 4 and job.repeat == 2 and job.slots == 2
    assert batch.waves(job) == [[0, 1], [2, 3]]
    assert job.startup_timeout_s == 120 and job.running_timeout_s == 1200
    slots = batch_runner.place(job, local_inventory)
    assert [(s.node, s.robots) for s in slots] == [("edge-1", ("fetch-1",)), ("edge-2", ("fetch-2",))]
    # a slot holds a whole run: every module's resources
    assert slots[0].cpu_millis == 1500 and slots[0].memory_bytes == (1024 + 512) * 2**20


def test_each_combination_is_an_indexed_job_with_its_values(local_inventory):
    job = load(NAV)
    slots = batch_runner.place(job, local_inventory)
    objects = batch.render_batch(job, slots)
    for obj in objects:
        kubernetes_validate.validate(obj, "1.34", strict=True)
    jobs = {o["metadata"]["name"]: o for o in objects if o["kind"] == "Job"}
    assert sorted(jobs) == ["nav-grid-0", "nav-grid-1", "nav-grid-2", "nav-grid-3"]
    third = jobs["nav-grid-2"]
    spec = third["spec"]
    assert (spec["completions"], spec["parallelism"], spec["completionMode"], spec["backoffLimitPerIndex"]) == (
        2,
        1,
        "Indexed",
        0,
    )
    pod = spec["template"]["spec"]
    assert pod["restartPolicy"] == "Never" and pod["activeDeadlineSeconds"] == 1200
    assert pod["nodeSelector"] == {"device.kuberos.io/hostname": "edge-1"}  # combination 2: slot 0, wave 1
    assert third["metadata"]["annotations"]["kuberos.io/batch-wave"] == "1"
    (main,) = pod["containers"]
    assert main["name"] == "evaluation" and main["args"][-2:] == ["world:=warehouse", "goal:=2.0,-1.0,0.0"]
    env = {e["name"]: e.get("value") for e in main["env"]}
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST" and "ROS_DISCOVERY_SERVER" not in env
    assert json.loads(env["KUBEROS_BATCH_PARAMETERS"]) == {"scenario.planner": "RRTConnect", "scenario.world": "warehouse"}
    (planner,) = pod["initContainers"]  # the other module: a native sidecar, stopped when the run ends
    assert planner["restartPolicy"] == "Always" and planner["envFrom"] == [{"configMapRef": {"name": "nav-grid-2-map-scenario"}}]
    maps = {o["metadata"]["name"]: o["data"] for o in objects if o["kind"] == "ConfigMap"}
    assert maps["nav-grid-2-map-scenario"] == {"world": "warehouse", "planner": "RRTConnect", "goal": "2.0,-1.0,0.0"}
    assert maps["nav-grid-1-map-scenario"]["planner"] == "PRM"


def test_the_reference_batch_job_runs_as_one_of_ours(local_inventory):
    job = load(GRASP)
    assert job.kind == "BatchJob" and job.name == "grasp-speed-sweep" and job.module == "grasp-trial"
    assert job.repeat == 2 and job.startup_timeout_s == 120 and job.running_timeout_s == 600
    assert [(a.map, a.key, a.values) for a in job.grid] == [
        ("grasp-parameters", "speed", ("0.1", "0.2", "0.4")),
        ("grasp-parameters", "object", ("cube", "cylinder")),
    ]
    job = batch.with_fleet(job, list(local_inventory.fleets))
    assert job.fleet == "test-fleet" and any("the runs go to fleet test-fleet" in n for n in job.notes)
    assert any("jobSpec.volume" in n for n in job.notes) and any("metadata.subname" in n for n in job.notes)
    objects = batch.render_batch(job, batch_runner.place(job, local_inventory))
    last = next(o for o in objects if o["kind"] == "Job" and o["metadata"]["name"] == "grasp-speed-sweep-5")
    (container,) = last["spec"]["template"]["spec"]["containers"]
    assert container["command"][-1] == "ros2 launch grasp_trial trial.launch.py speed:=0.4 object:=cylinder"
    for obj in objects:
        kubernetes_validate.validate(obj, "1.34", strict=True)


JOB = """
kind: RosBatchJob
metadata: {name: sweep, targetFleet: test-fleet}
job: {module: trial, grid: [{map: p, key: speed, values: [1, 2]}]}
parameterMaps: [{name: p, type: key-value, data: {speed: 1, mass: 2}}]
rosModules: [{name: trial, image: example/trial:1, launch: run, launchArguments: {speed: "{p.speed}"}}]
"""


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (("module: trial", "module: nope"), "job.module: 'nope' is not one of rosModules (trial)"),
        (
            ("key: speed, values", "key: size, values"),
            "job.grid[0].key: parameter map p has no key 'size'; its keys: speed, mass",
        ),
        (("map: p, key", "map: q, key"), "job.grid[0].map: 'q' is not a key-value parameter map of the job"),
        (("values: [1, 2]", "values: []"), "job.grid[0].values"),
        (("job: {module: trial,", "job: {module: trial, repeat: 0,"), "job.repeat"),
        (("job: {module: trial,", "job: {module: trial, runningTimeout: soon,"), "job.runningTimeout: 'soon' is not valid"),
        (("job: {module: trial,", "job: {module: trial, retries: 3,"), "job.retries"),
        (
            ("values: [1, 2]}]", f"values: {list(range(400))}}}, {{map: p, key: mass, values: {list(range(30))}}}]"),
            "job.grid: makes 12000 runs; expected at most 10000",
        ),
        (("kind: RosBatchJob", "kind: RosDeployment"), "kind: 'RosDeployment' is not a batch job"),
    ],
)
def test_bad_batch_jobs_name_the_field(change, expected):
    found = problems_of(JOB.replace(*change))
    assert any(expected in p for p in found), found


def test_reference_batch_job_errors_name_its_fields():
    text = open(GRASP, encoding="utf-8").read()
    found = problems_of(text.replace("rosModuleName: grasp-trial", "rosModuleName: missing"))
    assert any("jobSpec.lifecycleModule.rosModuleName: 'missing' is not one of rosModules" in p for p in found), found
    found = problems_of(text.replace("paramName: object", "paramName: colour"))
    expected = "jobSpec.varyingParameters[1].paramName: parameter map grasp-parameters has no key 'colour'"
    assert any(expected in p for p in found), found
    found = problems_of(text.replace("repeatNum: 2", "repeatNum: none"))
    assert any("jobSpec.lifecycleModule.repeatNum" in p for p in found), found
    assert problems_of("kind: BatchJob\nmetadata: {name: x}\njobSpec: 3\n")


def test_too_many_runs_at_once_say_so(local_inventory):
    job = batch.load_batch_jobs(
        JOB.replace("image: example/trial:1,", "image: example/trial:1, resources: {cpu: 100},"), "j.yml"
    )[0]
    with pytest.raises(KuberosError) as caught:
        batch_runner.place(job, local_inventory)
    assert "the runs of sweep cannot be placed: each run needs every module of the job on one node" in str(caught.value)
    assert "(cpu 100000m, memory 128Mi), 2 at once (job.parallelism)" in str(caught.value)
    assert "edge-1 (edge): cpu: needs 100, 15.9 free of 16" in str(caught.value)
    assert "(and 1 more runs at once alike; a lower job.parallelism needs fewer nodes at once)" in str(caught.value)


@pytest.mark.parametrize(
    ("status", "outcome"),
    [
        ({"phase": "Succeeded"}, ("succeeded", "")),
        (
            {
                "phase": "Failed",
                "reason": "DeadlineExceeded",
                "message": "Pod was active on the node longer than the specified deadline",
            },
            ("failed", "running timeout"),
        ),
        (
            {
                "phase": "Failed",
                "containerStatuses": [{"name": "trial", "state": {"terminated": {"exitCode": 3, "reason": "Error"}}}],
            },
            ("failed", "trial exited 3 (Error)"),
        ),
        ({"phase": "Running"}, ("running", "")),
        ({"phase": "Pending"}, ("pending", "")),
    ],
)
def test_a_pods_status_becomes_the_runs_outcome(status, outcome):
    assert batch_runner._outcome({"status": status}) == outcome


class FakeCluster:
    """Pods as the API server reports them, to drive the watch's bookkeeping (the cluster test drives a real one)."""

    def __init__(self, pods):
        self.pods_now, self.deleted = pods, []

    def pods(self, namespace, name):
        return self.pods_now

    def delete_pod(self, namespace, name):
        self.deleted.append(name)

    def log(self, namespace, pod, container):
        return f"log of {container}\n"


def test_a_run_that_does_not_start_in_time_is_stopped_and_failed(tmp_path, local_inventory):
    job = batch.load_batch_jobs(JOB.replace("job: {module: trial,", "job: {module: trial, startupTimeout: 5 s,"), "j.yml")[0]
    slots = batch_runner.place(job, local_inventory)
    rows = batch_runner.plan_rows(job, slots)
    pending = {
        "metadata": {"name": "sweep-0-0-abc", "labels": {batch.RUN: "0", batch_runner.INDEX_LABEL: "0"}},
        "spec": {"nodeName": None, "containers": [{"name": "trial"}]},
        "status": {"phase": "Pending"},
    }
    cluster = FakeCluster([pending])
    lines = []
    watch = batch_runner.Watch(job, rows, cluster, str(tmp_path), lines.append, 0.0)
    watch.observe(0, now=100.0)
    assert watch.runs[(0, 0)]["state"] == "pending" and not cluster.deleted
    watch.observe(0, now=106.0)
    assert watch.runs[(0, 0)]["state"] == "failed" and "startup timeout" in watch.runs[(0, 0)]["why"]
    assert cluster.deleted == ["sweep-0-0-abc"]
    assert os.path.exists(tmp_path / "runs" / "0-0" / "result.json")


@pytest.mark.parametrize(
    "enforced, needed, labels",
    [
        (None, "baseline", {"pod-security.kubernetes.io/enforce": "baseline"}),  # a new namespace: what the runs need
        (None, None, {"pod-security.kubernetes.io/enforce": "restricted"}),
        ("baseline", "restricted", {}),  # enforced by its deployments: left to them
        ("privileged", "baseline", {}),
    ],
)
def test_a_batch_runs_namespace_keeps_the_level_its_deployments_enforce(enforced, needed, labels):
    namespace = batch_runner._batch_namespace("kuberos-lab", enforced, needed)
    got = {k: v for k, v in namespace["metadata"]["labels"].items() if k == "pod-security.kubernetes.io/enforce"}
    assert got == labels


def test_a_batch_run_that_needs_more_than_its_namespace_enforces_is_refused_before_anything_runs():
    with pytest.raises(batch_runner.KuberosError) as error:
        batch_runner._batch_namespace("kuberos-lab", "restricted", "baseline")
    assert str(error.value).startswith("namespace kuberos-lab enforces the restricted Pod Security level, and this batch")
