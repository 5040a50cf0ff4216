"""Software lifecycle against the real local control plane, with the controller running throughout.

The pick-and-place app is deployed from the software catalog (examples/pick-and-place-catalog.yml, every module at
0.1.0) and then: a second deployment in the same fleet moves and restarts nothing of the first; a rollout to 0.2.0
goes canary first, then wave by wave, through the health gates; a broken version (its pods crash-loop) stops at the
canary and is rolled back with nothing else touched; a rollback returns to revision 1; a node that fails during a
rollout ends it in the documented state. After each, every module runs exactly once where the record says, and the
status table tells the truth (versions, phases) within one resync.

A crash-looping container cannot exist on kwok nodes (nothing runs in their pods): the test marks the broken
version's pods the way a kubelet would (restarts, CrashLoopBackOff) as soon as they appear.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import threading
import time

import pytest
import yaml
from helpers import ROOT, playbook
from test_controller import NAMESPACE, Fleet, wait_for

pytestmark = pytest.mark.cluster

CATALOG = os.path.join(ROOT, "inventories", "local", "catalog")
SPEC = os.path.join(ROOT, "examples", "pick-and-place-catalog.yml")
FIRST = "pick-and-place"
BROKEN_TAG = "0.2.1-crashloop"


def _spec(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def _at(tmp_path, version_range: str):
    """The catalog spec with every module at ``version_range``."""
    with open(SPEC, encoding="utf-8") as handle:
        text = handle.read()
    return _spec(tmp_path, f"pnp-{version_range.strip('^')}.yml", text.replace("@^0.1", f"@{version_range}"))


class Lifecycle(Fleet):
    def run(self, name, *extra, timeout=600):
        return playbook(name, "-e", f"kuberos_kubeconfig={self.cluster.kubeconfig}", "-e", f"kuberos_catalog={self.catalog}",
                        *[str(e) for e in extra], timeout=timeout)  # fmt: skip

    def rollout(self, spec, *extra):
        return self.run("rollout.yml", "-e", f"rosdeployment_file={spec}", "-e", "rosdeployment_rollout_soak=2", *extra)

    def images(self) -> dict[str, str]:
        return {
            d.metadata.name: d.spec.template.spec.containers[0].image
            for d in self.apps.list_namespaced_deployment(
                NAMESPACE, label_selector=f"kuberos.io/deployment={FIRST},kuberos.io/component=ros-module"
            ).items
        }

    def versions(self, kind="Deployment") -> dict[str, str]:
        if kind == "Deployment":
            items = self.apps.list_namespaced_deployment(NAMESPACE).items
        else:
            items = self.core.list_namespaced_pod(NAMESPACE).items
        return {o.metadata.name: o.metadata.resource_version for o in items}

    def pod_uids(self, prefix="") -> dict[str, str]:
        return {
            p.metadata.name: p.metadata.uid
            for p in self.core.list_namespaced_pod(NAMESPACE).items
            if p.metadata.name.startswith(prefix) and not p.metadata.deletion_timestamp
        }

    def status_rows(self):
        return {(r["robot"], r["module"]): r for r in self.status()["rows"]}

    def wait_status(self, check, what):
        wait_for(lambda: check(self.status_rows()), 40, what, lambda: json.dumps(self.status()["rows"], indent=1)[-3000:])


@pytest.fixture(scope="module")
def life(cluster, tmp_path_factory):
    state = tmp_path_factory.mktemp("lifecycle")
    fleet = Lifecycle(cluster, state)
    fleet.catalog = CATALOG
    # From a clean fleet: earlier tests may leave pick-and-place (the same deployment name) deployed.
    cleared = fleet.run("undeploy.yml", "-e", f"rosdeployment_file={SPEC}")
    assert cleared.returncode == 0, cleared.stdout[-3000:]
    deployed = fleet.run("deploy.yml", "-e", f"rosdeployment_file={SPEC}", "-e", f"kuberos_render_dir={state / 'render'}")
    assert deployed.returncode == 0, deployed.stdout[-4000:]
    started = fleet.controller()
    assert started.returncode == 0, started.stdout[-3000:]
    try:
        fleet.converge()
        yield fleet
    finally:
        fleet.controller("stopped")
        fleet.restore_nodes()
        fleet.run("undeploy.yml", "-e", f"rosdeployment_file={SPEC}")


def test_deployed_from_the_catalog_with_versions_and_revision_1(life):
    record = life.record()
    assert record.revision == 1
    assert {m.name: m.version for m in record.spec.modules} == {
        "perception": "0.1.0", "motion-planner": "0.1.0", "controller": "0.1.0", "task-coordinator": "0.1.0",
    }  # fmt: skip
    assert set(life.images().values()) >= {"ghcr.io/kuberos/pnp-planner:0.1"}
    life.wait_status(lambda rows: rows[("fetch-1", "motion-planner")]["version"] == "0.1.0", "the version in the status")
    table = playbook("status.yml", "-e", f"kuberos_kubeconfig={life.cluster.kubeconfig}")
    assert "VERSION" in table.stdout and "pick-and-place (revision 1)" in table.stdout, table.stdout[-3000:]


def test_a_second_deployment_in_the_fleet_moves_and_restarts_nothing_of_the_first(life, tmp_path):
    pods = life.pod_uids()
    discovery = {k: v for k, v in life.versions().items() if k.startswith("kuberos-discovery-")}
    first = {k: v for k, v in life.versions().items() if k.startswith(FIRST)}
    placed = life.placed()
    second = os.path.join(ROOT, "examples", "listing1.yml")
    deployed = life.run("deploy.yml", "-e", f"rosdeployment_file={second}", "-e", f"kuberos_render_dir={tmp_path / 'second'}")
    assert deployed.returncode == 0, deployed.stdout[-4000:]
    try:
        after = life.versions()
        assert {k: after[k] for k in discovery} == discovery, "the fleet's discovery servers were not touched"
        assert {k: after[k] for k in first} == first, "no Deployment of the first deployment changed"
        now = life.pod_uids()
        assert {k: now.get(k) for k in pods} == pods, "no pod of the first deployment or of the fleet restarted"
        assert life.placed() == placed
        # Status tells the truth within one resync: the discovery rows are Running where they run.
        life.wait_status(
            lambda rows: all(r["phase"] == "Running" for r in rows.values()), "every row of the first deployment Running"
        )
    finally:
        removed = life.run("undeploy.yml", "-e", f"rosdeployment_file={second}")
        assert removed.returncode == 0, removed.stdout[-3000:]
    assert {k: v for k, v in life.pod_uids().items() if k in pods} == pods, "undeploying the second moved nothing either"
    life.converge()


def test_check_and_diff_show_each_robots_changes_and_write_nothing(life, tmp_path):
    before = life.versions()
    checked = life.rollout(_at(tmp_path, "^0.2"), "--check", "--diff")
    assert checked.returncode == 0, checked.stdout[-4000:]
    assert "+fetch-1:" in checked.stdout and "+fetch-2:" in checked.stdout
    planner = "image ghcr.io/kuberos/pnp-planner:0.1 -> ghcr.io/kuberos/pnp-planner:0.2.0"
    assert f"motion-planner: update (version 0.1.0 -> 0.2.0; {planner})" in checked.stdout
    assert "revision 1 -> 2 (check mode: nothing written)" in checked.stdout
    assert life.versions() == before
    assert life.record().revision == 1


def test_a_rollout_upgrades_every_robot_canary_first_then_in_waves(life, tmp_path):
    discovery = life.pod_uids("kuberos-discovery-")
    done = life.rollout(_at(tmp_path, "^0.2"), "-e", "rosdeployment_rollout_wave_size=1")
    assert done.returncode == 0, done.stdout[-5000:]
    assert "canary: " in done.stdout and "wave 2: 1 robot(s)" in done.stdout, done.stdout[-3000:]
    assert "revision 1 -> 2" in done.stdout
    assert all(image.endswith(":0.2.0") for image in life.images().values()), life.images()
    record = life.record()
    assert record.revision == 2 and record.rollout is None
    assert {m.version for m in record.spec.modules} == {"0.2.0"}
    assert life.pod_uids("kuberos-discovery-") == discovery, "the fleet's discovery servers were not touched"
    life.converge()
    life.wait_status(lambda rows: {r["version"] for k, r in rows.items() if k[0] != "-"} == {"0.2.0"}, "0.2.0 everywhere")
    again = life.rollout(_at(tmp_path, "^0.2"))
    assert again.returncode == 0 and again.changed == 0, again.stdout[-3000:]
    assert "nothing to change" in again.stdout


def test_deploy_and_a_second_rollout_refuse_while_a_rollout_is_in_progress(life, tmp_path):
    record = "kuberos-record-pick-and-place"
    marker = json.dumps({"revision": 9, "from": 2, "instances": [], "started": "2026-01-01T00:00:00Z"})
    life.core.patch_namespaced_config_map(record, NAMESPACE, {"data": {"rollout.json": marker}})
    before = life.versions()
    try:
        deploy = life.run("deploy.yml", "-e", f"rosdeployment_file={SPEC}", "-e", f"kuberos_render_dir={tmp_path / 'r'}")
        assert deploy.returncode != 0 and "a rollout of pick-and-place is in progress" in deploy.stdout, deploy.stdout[-3000:]
        again = life.rollout(_at(tmp_path, "^0.1"))
        assert again.returncode != 0 and "in progress since 2026-01-01T00:00:00Z" in again.stdout, again.stdout[-3000:]
        assert life.versions() == before, "nothing was written"
    finally:
        life.core.patch_namespaced_config_map(record, NAMESPACE, {"data": {"rollout.json": None}})
    life.converge()


def _broken_catalog(tmp_path) -> str:
    """The example catalog plus pnp-planner 0.2.1, whose image crash-loops."""
    folder = tmp_path / "catalog"
    folder.mkdir()
    with open(os.path.join(CATALOG, "pick-and-place.yml"), encoding="utf-8") as handle:
        documents = list(yaml.safe_load_all(handle))
    planner = next(m for m in documents[0]["modules"] if m["name"] == "pnp-planner")
    broken = copy.deepcopy(next(v for v in planner["versions"] if v["version"] == "0.2.0"))
    broken.update(version="0.2.1", image=f"ghcr.io/kuberos/pnp-planner:{BROKEN_TAG}")
    planner["versions"].append(broken)
    (folder / "pick-and-place.yml").write_text(yaml.safe_dump_all(documents, sort_keys=False))
    return str(folder)


class CrashLooper(threading.Thread):
    """Marks every pod of the broken image as a kubelet would report a crash-looping container, again whenever its
    status shows otherwise: kwok writes a Running status of its own when it takes up a new pod, and a mark made just
    before that is overwritten (then the canary's gate saw a Ready pod and let the broken version through)."""

    def __init__(self, core):
        super().__init__(daemon=True)
        self.core = core
        self.stop = threading.Event()
        self.marked: set[str] = set()

    def run(self):
        deadline = time.monotonic() + 300
        while not self.stop.is_set() and time.monotonic() < deadline:
            for pod in self.core.list_namespaced_pod(NAMESPACE).items:
                image = pod.spec.containers[0].image
                if not image.endswith(BROKEN_TAG) or pod.metadata.deletion_timestamp or _crash_looping(pod):
                    continue
                statuses = [{
                    "name": c.name, "ready": False, "restartCount": 3, "image": c.image, "imageID": "", "started": False,
                    "state": {"waiting": {"reason": "CrashLoopBackOff", "message": "back-off restarting failed container"}},
                } for c in pod.spec.containers]  # fmt: skip
                try:
                    self.core.patch_namespaced_pod_status(
                        pod.metadata.name, NAMESPACE, {"status": {"containerStatuses": statuses}}
                    )
                    self.marked.add(pod.metadata.name)
                except Exception:
                    pass
            time.sleep(0.2)


def _crash_looping(pod) -> bool:
    return any(
        s.state and s.state.waiting and s.state.waiting.reason == "CrashLoopBackOff" for s in pod.status.container_statuses or []
    )


def test_a_broken_version_stops_at_the_canary_and_only_the_canary_is_rolled_back(life, tmp_path):
    life.catalog = _broken_catalog(tmp_path)
    spec = _spec(tmp_path, "broken.yml", _at(tmp_path, "^0.2").read_text().replace("pnp-planner@^0.2", "pnp-planner@0.2.1"))
    before = life.versions()
    images = life.images()
    looper = CrashLooper(life.core)
    looper.start()
    try:
        failed = life.rollout(spec, "-e", '{"rosdeployment_rollout_canary_robots": ["fetch-1"]}')
    finally:
        looper.stop.set()
        life.catalog = CATALOG
    assert failed.returncode != 0, failed.stdout[-3000:]
    assert "stopped at the canary" in failed.stdout and "CrashLoopBackOff" in failed.stdout, failed.stdout[-3000:]
    assert "rolled back robots fetch-1" in failed.stdout
    assert looper.marked, "the broken version's pod was started on the canary"
    after = life.versions()
    assert after["pick-and-place-motion-planner-fetch-2"] == before["pick-and-place-motion-planner-fetch-2"], "fetch-2 untouched"
    assert life.images() == images, "the canary runs its previous version again"
    record = life.record()
    assert record.revision == 2 and record.rollout is None
    life.converge()
    life.wait_status(lambda rows: rows[("fetch-1", "motion-planner")]["phase"] == "Running", "the canary Running again")


def test_rollback_returns_to_revision_1_as_a_new_revision(life):
    back = life.run(
        "rollback.yml", "-e", f"rosdeployment_file={SPEC}", "-e", "rosdeployment_revision=1", "-e", "rosdeployment_rollout_soak=1"
    )
    assert back.returncode == 0, back.stdout[-4000:]
    assert "revision 2 -> 3" in back.stdout
    assert all(":0.1" in image for image in life.images().values()), life.images()
    record = life.record()
    assert record.revision == 3 and {m.version for m in record.spec.modules} == {"0.1.0"}
    missing = life.run("rollback.yml", "-e", f"rosdeployment_file={SPEC}", "-e", "rosdeployment_revision=42")
    assert missing.returncode != 0 and "42 is not a kept revision (kept: 1, 2, 3)" in missing.stdout, missing.stdout[-2000:]
    life.converge()


def test_a_node_failure_during_a_rollout_stops_it_and_the_controller_then_moves_the_modules(life, tmp_path):
    """The defined state: the gate fails, the touched robots get their previous objects back, the record keeps its
    revision and loses the rollout marker; then the controller moves what ran on the failed node."""
    planner = "pick-and-place-motion-planner-fetch-1"
    node = life.placed()[planner]
    command = [
        os.path.join(ROOT, ".venv", "bin", "ansible-playbook"), "playbooks/rollout.yml",
        "-e", f"kuberos_kubeconfig={life.cluster.kubeconfig}", "-e", f"kuberos_catalog={CATALOG}",
        "-e", f"rosdeployment_file={_at(tmp_path, '^0.2')}", "-e", "rosdeployment_rollout_soak=20",
        "-e", "rosdeployment_rollout_gate_timeout=20", "-e", '{"rosdeployment_rollout_canary_robots": ["fetch-1"]}',
    ]  # fmt: skip
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1"}
    running = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(lambda: life.record().rollout is not None, 60, "the rollout marker on the record")
        wait_for(lambda: life.images()[planner].endswith(":0.2.0"), 60, "the canary's planner replaced")
        life.node_down(node)
        out, _ = running.communicate(timeout=180)
    finally:
        if running.poll() is None:
            running.kill()
    try:
        assert running.returncode != 0, out[-3000:]
        assert "stopped at the canary" in out, out[-3000:]
        record = life.record()
        assert record.revision == 3 and record.rollout is None
        assert life.images()[planner].endswith(":0.1"), "the canary has its previous objects back"
        wait_for(lambda: life.placed()[planner] != node, 60, f"the controller moving {planner} off {node}")
        life.converge()
    finally:
        life.node_up(node)
    life.converge()


def test_a_ros_probe_that_does_not_find_the_waves_nodes_fails_the_gate(life, tmp_path):
    """The probe runs for real (rclpy, Fast DDS) after the canary's soak; with no discovery server to reach (the kwok
    pods run no ROS node), it exits 1 and the canary is rolled back."""
    import sys

    probe = [
        "env", f"ROS_DISCOVERY_SERVER=127.0.0.1:{_free_port()}", f"ROS_LOG_DIR={tmp_path}", "ROS_DOMAIN_ID=23",
        f"PYTHONPATH={os.path.join(ROOT, '.collections')}", os.path.join(sys.prefix, "bin", "python3"),
        "-m", "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.ros_graph_probe",
        "--expect", "/{robot}/motion_planner", "--timeout", "2",
    ]  # fmt: skip
    images = life.images()
    failed = life.rollout(
        _at(tmp_path, "^0.2"),
        "-e",
        json.dumps({"rosdeployment_rollout_ros_probe": probe, "rosdeployment_rollout_canary_robots": ["fetch-1"]}),
    )
    assert failed.returncode != 0, failed.stdout[-3000:]
    assert "the ROS probe failed (exit 1)" in failed.stdout and "missing after 2 s: /fetch_1/motion_planner" in failed.stdout
    assert life.images() == images and life.record().rollout is None
    life.converge()


def test_a_rollout_leaves_an_offline_robot_pending_and_the_next_run_finishes_it(life, tmp_path):
    """fetch-2 offline: the rollout upgrades fetch-1 and reports fetch-2 pending, touching none of fetch-2's modules
    and waiting for nothing; with fetch-2 back, the same rollout run again upgrades it (as its own canary)."""
    spec = _at(tmp_path, "^0.2")
    before = life.images()
    assert not any(image.endswith(":0.2.0") for image in before.values()), before
    theirs = {name for name in before if name.endswith("-fetch-2")}
    untouched = {k: v for k, v in life.versions().items() if k in theirs}
    life.node_down("fetch-2")
    try:
        started = time.monotonic()
        done = life.rollout(spec, "-e", "rosdeployment_rollout_wave_size=1")
        took = time.monotonic() - started
        assert done.returncode == 0, done.stdout[-5000:]
        assert "pending, offline (the next rollout run finishes them): fetch-2" in done.stdout, done.stdout[-3000:]
        images = life.images()
        assert all(images[n].endswith(":0.2.0") for n in images if n.endswith("-fetch-1")), images
        assert {n: images[n] for n in theirs} == {n: before[n] for n in theirs}, "fetch-2's modules were not touched"
        assert {k: v for k, v in life.versions().items() if k in theirs} == untouched
        assert took < 120, f"the rollout waited for the offline robot ({took:.0f} s)"
        revision = life.record().revision
    finally:
        life.node_up("fetch-2")
    again = life.rollout(spec)
    assert again.returncode == 0, again.stdout[-5000:]
    assert "fetch-2: " in again.stdout and "fetch-1: " not in again.stdout, again.stdout[-3000:]
    assert "canary: 1 robot(s) in" in again.stdout and "pending, offline" not in again.stdout, again.stdout[-3000:]
    assert all(image.endswith(":0.2.0") for image in life.images().values()), life.images()
    assert life.record().revision == revision, "the same revision, now on every robot"
    life.converge()


def test_a_robot_holding_its_update_lock_is_left_pending_and_the_next_run_finishes_it(life, tmp_path):
    """The update lock command says fetch-1 holds its lock (exit 1, ``held: fetch-1``): the rollout (back to 0.1)
    upgrades fetch-2 and leaves fetch-1 pending, touching none of its modules; run again with the lock free, it
    finishes fetch-1. A lock command that cannot answer leaves its wave's robots pending too."""
    spec = _at(tmp_path, "^0.1")
    before = life.images()
    assert all(image.endswith(":0.2.0") for image in before.values()), before
    locked = [
        "sh", "-c", 'case ",$KUBEROS_ROBOTS," in *,fetch-1,*) echo "held: fetch-1"; exit 1;; esac; exit 0',
    ]  # fmt: skip
    done = life.rollout(
        spec, "-e", json.dumps({"rosdeployment_rollout_update_lock": locked, "rosdeployment_rollout_wave_size": 1})
    )
    assert done.returncode == 0, done.stdout[-5000:]
    assert "pending, update lock (the next rollout run finishes them): fetch-1 (update lock held)" in done.stdout, done.stdout[
        -3000:
    ]
    images = life.images()
    fetch_1 = {n: images[n] for n in images if n.endswith("-fetch-1")}
    assert fetch_1 == {n: before[n] for n in fetch_1}, "fetch-1's modules were not touched"
    assert all(images[n].endswith(":0.1") for n in images if n.endswith("-fetch-2")), images
    broken = ["sh", "-c", "exit 7"]
    unknown = life.rollout(spec, "-e", json.dumps({"rosdeployment_rollout_update_lock": broken}))
    assert unknown.returncode == 0, unknown.stdout[-5000:]
    assert "fetch-1 (the update lock could not be checked (exit 7" in unknown.stdout, unknown.stdout[-3000:]
    assert life.images() == images, "a lock that cannot be checked touches nothing"
    again = life.rollout(spec)
    assert again.returncode == 0, again.stdout[-5000:]
    assert all(image.endswith(":0.1") for image in life.images().values()), life.images()
    life.converge()


def _free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]
