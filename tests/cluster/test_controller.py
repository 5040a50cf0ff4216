"""The controller against the real local control plane: faults injected, modules moved, nothing lost.

The pick-and-place example is deployed to test-fleet with playbooks/deploy.yml and the controller is
started with playbooks/controller.yml (grace 2 s; two replicas, one leads on the Lease). Each test
injects one fault the way it shows in a real cluster (a kwok node whose heartbeats stop and whose Ready
condition turns Unknown, a Node deleted, a pod that keeps restarting, a measured RTT above max_latency,
the leader killed between its two writes or while a node is failing, the leader paused past its Lease,
the leader's own node NotReady, the API server restarted), then checks the invariant: every module
instance of every robot runs exactly once, Running and Ready, on the node the deployment record says, and
the record is what the scheduler keeps given the faults (``replace_modules`` moves nothing more).
"""

from __future__ import annotations

import datetime
import glob
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest
from helpers import free_ports, inventory_raw, playbook

pytestmark = pytest.mark.cluster

SPEC = "examples/pick-and-place.yml"
NAMESPACE = "kuberos-test-fleet"
RECORD = "kuberos-record-pick-and-place"
STATUS = "kuberos-status-pick-and-place"
GRACE = 2
KWOK = "kwok.x-k8s.io/node"
RTT = "kuberos.io/rtt-ms"
LEASE = ("kuberos-controller", "kuberos-system")
ENTRY = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller"


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


class Fleet:
    def __init__(self, cluster, state_dir):
        self.cluster = cluster
        self.state_dir = str(state_dir)
        self.core, self.apps, _ = cluster.clients()
        from kubernetes import client

        self.coordination = client.CoordinationV1Api(self.core.api_client)
        self.dashboard_port = free_ports(2)  # the replicas' dashboards, never a developer's own controller's port

    def dashboard(self, replica: int) -> str:
        """The address of replica ``replica``'s (1-based) dashboard and /metrics."""
        return f"http://127.0.0.1:{self.dashboard_port + replica - 1}/"

    # -- the controller, through its playbook ------------------------------------------------
    def controller(self, state="started", env=None, timeout=120):
        extra = {
            "controller_kubeconfig": self.cluster.kubeconfig,
            "controller_state_dir": self.state_dir,
            "controller_grace": GRACE,
            "controller_state": state,
            "controller_dashboard_port": self.dashboard_port,
        }
        old = {k: os.environ.get(k) for k in (env or {})}
        os.environ.update(env or {})
        try:
            return playbook("controller.yml", "-e", json.dumps(extra), timeout=timeout)
        finally:
            for key, value in old.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value

    def log(self) -> str:
        """Every replica's log, one after the other."""
        text = ""
        for path in sorted(glob.glob(os.path.join(self.state_dir, "*.log"))):
            with open(path, encoding="utf-8", errors="replace") as handle:
                text += handle.read()
        return text

    def pids(self) -> list[int]:
        """Pids of the replicas that run now."""
        found = []
        for path in sorted(glob.glob(os.path.join(self.state_dir, "controller*.pid"))):
            try:
                with open(path, encoding="utf-8") as handle:
                    pid = int(handle.read())
                with open(f"/proc/{pid}/cmdline", "rb") as handle:
                    if b"kuberos_controller" in handle.read() and _state(pid) != "Z":
                        found.append(pid)
            except (OSError, ValueError):
                continue
        return found

    def leader(self) -> str:
        """The Lease's holder ('' when free or absent)."""
        from kubernetes.client.exceptions import ApiException

        try:
            lease = self.coordination.read_namespaced_lease(*LEASE)
        except ApiException:
            return ""
        return lease.spec.holder_identity or ""

    def leader_pid(self, timeout=30) -> int:
        """The pid of the replica that leads (identities of local replicas are host_pid)."""
        prefix = socket.gethostname() + "_"
        wait_for(lambda: self.leader().startswith(prefix) and int(self.leader()[len(prefix) :]) in self.pids(), timeout,
                 "a running replica holding the Lease", lambda: f"holder {self.leader()!r}, replicas {self.pids()}")  # fmt: skip
        return int(self.leader()[len(prefix) :])

    def moved_by(self) -> dict[str, set]:
        """Instance -> the identities of the replicas that reported moving it (ModuleMoved events)."""
        found: dict[str, set] = {}
        for event in self.events("ModuleMoved"):
            found.setdefault(event.involved_object.name, set()).add(event.reporting_instance or "")
        return found

    # -- faults ------------------------------------------------------------------------------
    def node_down(self, name):
        """What a dead kubelet looks like: no heartbeats (kwok lets go of the node) and Ready=Unknown."""
        self.core.patch_node(name, {"metadata": {"annotations": {KWOK: None}}})
        condition = {
            "type": "Ready", "status": "Unknown", "reason": "NodeStatusUnknown", "message": "Kubelet stopped posting status.",
            "lastTransitionTime": _now(), "lastHeartbeatTime": _now(),
        }  # fmt: skip
        self.core.patch_node_status(name, {"status": {"conditions": [condition]}})

    def node_up(self, name):
        self.core.patch_node(name, {"metadata": {"annotations": {KWOK: "fake"}}})
        wait_for(lambda: self.ready(name), 60, f"node {name} Ready again")

    def restore_nodes(self):
        """Leave every node as the cluster fixture made it (kwok heartbeats again, Ready)."""
        for node in self.core.list_node().items:
            if (node.metadata.annotations or {}).get(KWOK) != "fake":
                self.node_up(node.metadata.name)

    def ready(self, name) -> bool:
        try:
            node = self.core.read_node(name)
        except Exception:
            return False
        return _ready(node)

    # -- reading back ------------------------------------------------------------------------
    def record(self):
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import parse_record

        configmap = self.core.read_namespaced_config_map(RECORD, NAMESPACE)
        return parse_record(self.core.api_client.sanitize_for_serialization(configmap))

    def placed(self) -> dict[str, str]:
        return self.record().placement.pinned()

    def pods(self) -> dict[str, list]:
        found: dict[str, list] = {}
        for pod in self.core.list_namespaced_pod(NAMESPACE, label_selector="app.kubernetes.io/managed-by=kuberos").items:
            found.setdefault(pod.metadata.labels.get("kuberos.io/instance"), []).append(pod)
        return found

    def down_nodes(self) -> dict[str, str]:
        names = {n.metadata.name for n in self.core.list_node().items if not self.ready(n.metadata.name)}
        present = {n.metadata.name for n in self.core.list_node().items}
        down = {n: f"{n} is down" for n in names}
        down.update({n: f"{n} is gone" for n in self.record().inventory.nodes if n not in present})
        return down

    def problems(self, allow_stranded=()) -> list[str]:
        """Everything that breaks the invariant now (empty when it holds)."""
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.replacement import replace_modules

        record = self.record()
        placed = self.placed()
        pods = self.pods()
        problems = []
        for instance, node in sorted(placed.items()):
            live = [p for p in pods.get(instance, []) if not p.metadata.deletion_timestamp]
            running = [p for p in live if p.status.phase == "Running" and _ready(p)]
            if instance in allow_stranded:
                continue
            if len(live) != 1 or len(running) != 1 or running[0].spec.node_name != node:
                problems.append(
                    f"{instance}: placed on {node}, pods {[(p.metadata.name, p.spec.node_name, p.status.phase) for p in live]}"
                )
        for instance in set(pods) - set(placed):
            problems.append(f"{instance}: pods of an instance that is not placed")
        again = replace_modules(record.deployments, record.inventory, record.placement, unavailable=self.down_nodes())
        problems += [f"{m.instance} should move from {m.from_node}: {m.why}" for m in again.moves]
        return problems

    def converge(self, timeout=60, allow_stranded=()):
        last = []

        def ok():
            nonlocal last
            last = self.problems(allow_stranded)
            return not last

        wait_for(ok, timeout, "every module running exactly once where the record says", lambda: "\n".join(last))

    def events(self, reason) -> list:
        return [e for e in self.core.list_namespaced_event(NAMESPACE).items if e.reason == reason]

    def status(self) -> dict:
        configmap = self.core.read_namespaced_config_map(STATUS, NAMESPACE)
        return json.loads(configmap.data["status.json"])

    def busiest_edge(self) -> tuple[str, list[str]]:
        placed = self.placed()
        edges = [n for n in sorted(set(placed.values())) if n.startswith("edge-")]
        node = max(edges, key=lambda n: sum(1 for v in placed.values() if v == n))
        return node, sorted(i for i, n in placed.items() if n == node)


def _state(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8") as handle:
            return handle.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return ""


def _ready(obj) -> bool:
    return any(c.type == "Ready" and c.status == "True" for c in obj.status.conditions or [])


def wait_for(check, timeout, what, detail=lambda: ""):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.3)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}\n{detail()}")


@pytest.fixture(scope="module")
def fleet(cluster, tmp_path_factory):
    render = tmp_path_factory.mktemp("render-controller")
    deployed = cluster.deploy(SPEC, render)
    assert deployed.returncode == 0, deployed.stdout[-4000:]
    fleet = Fleet(cluster, tmp_path_factory.mktemp("controller"))
    started = fleet.controller()
    assert started.returncode == 0, started.stdout[-3000:]
    try:
        fleet.converge()
        yield fleet
    finally:
        fleet.controller("stopped")
        fleet.restore_nodes()
        restored = cluster.start()  # recreates deleted nodes from the inventory
        assert restored.returncode == 0, restored.stdout[-3000:]
        cluster.undeploy(SPEC)


def test_a_not_ready_node_loses_its_modules_and_only_those_move(fleet):
    node, leaving = fleet.busiest_edge()
    before = fleet.placed()
    moved_events = len(fleet.events("ModuleMoved"))
    fleet.node_down(node)
    try:
        fleet.converge()
        after = fleet.placed()
        assert {i for i in before if before[i] != after[i]} == set(leaving), "only the dead node's instances move"
        assert node not in after.values()
        assert len(fleet.events("ModuleMoved")) >= moved_events + len(leaving)
        rows = {r["instance"]: r for r in fleet.status()["rows"]}
        for instance in leaving:
            assert rows[instance]["phase"] == "Running"
            assert rows[instance]["last_move"]["from"] == node and "NotReady" in rows[instance]["last_move"]["why"]
        table = playbook("status.yml", "-e", f"kuberos_kubeconfig={fleet.cluster.kubeconfig}")
        assert table.returncode == 0 and f"from {node}: node {node} is NotReady" in table.stdout, table.stdout[-3000:]
    finally:
        fleet.node_up(node)
    time.sleep(GRACE + 2)
    assert fleet.placed() == after, "a recovered node does not pull modules back (no ping-pong)"
    fleet.converge()


def test_a_short_blip_inside_the_grace_period_moves_nothing(fleet):
    node, _ = fleet.busiest_edge()
    before = fleet.placed()
    fleet.node_down(node)
    time.sleep(GRACE / 4)
    fleet.node_up(node)
    time.sleep(GRACE + 2)
    assert fleet.placed() == before
    fleet.converge()


def test_a_deleted_node_loses_its_modules(fleet):
    node, _ = fleet.busiest_edge()
    fleet.core.delete_node(node)
    try:
        fleet.converge()
        assert node not in fleet.placed().values()
        assert "is not in the cluster" in fleet.log()
    finally:
        restored = fleet.cluster.start()  # the local_cluster playbook creates the inventory's nodes again
        assert restored.returncode == 0, restored.stdout[-3000:]
        wait_for(lambda: fleet.ready(node), 60, f"{node} back")
    fleet.converge()


def test_an_offline_robot_keeps_its_modules_and_is_reported_offline_not_stranded(fleet):
    """A robot's computer that stops reporting is a robot offline, not a failed node: nothing moves, its onboard
    module is shown Offline (not Stranded), one RobotOffline event, and RobotOnline once it is back."""
    before = fleet.placed()
    onboard = "pick-and-place-controller-fetch-1"
    seen = {e.metadata.uid for e in fleet.core.list_namespaced_event(NAMESPACE).items}

    def new(reason):  # the events of this test (the list is in no order: earlier tests' are told apart by UID)
        return [e for e in fleet.events(reason) if e.metadata.uid not in seen]

    fleet.node_down("fetch-1")
    try:
        wait_for(
            lambda: any(r["instance"] == onboard and r["phase"] == "Offline" for r in fleet.status()["rows"]),
            30,
            "the onboard controller module shown Offline",
        )
        row = next(r for r in fleet.status()["rows"] if r["instance"] == onboard)
        assert row["note"].startswith("robot offline since ") and "node fetch-1 is NotReady" in row["note"], row
        assert fleet.placed() == before, "nothing moves"
        offline = new("RobotOffline")
        assert [e.involved_object.name for e in offline] == [onboard], [e.message for e in offline]
        assert offline[0].message.startswith("robot fetch-1 is offline (node fetch-1 is NotReady")
        assert "controller stays on fetch-1, nothing moves or restarts" in offline[0].message
        assert new("ModuleStranded") == [], "an offline robot strands nothing"
        fleet.converge(allow_stranded={onboard})
    finally:
        fleet.node_up("fetch-1")
    wait_for(
        lambda: all(r["phase"] == "Running" for r in fleet.status()["rows"] if r["instance"] == onboard),
        30,
        "the onboard module running again",
    )
    wait_for(lambda: new("RobotOnline"), 30, "a RobotOnline event")
    assert [e.involved_object.name for e in new("RobotOnline")] == [onboard]
    assert len(new("RobotOffline")) == 1, "said once"
    assert new("ModuleMoved") == []
    fleet.converge()


def test_a_measured_latency_above_max_latency_moves_the_module(fleet):
    instance = "pick-and-place-perception-fetch-2"  # max_latency 20 ms
    node = fleet.placed()[instance]
    fleet.core.patch_node("fetch-2", {"metadata": {"annotations": {RTT: json.dumps({node: 45.0})}}})
    try:
        wait_for(lambda: fleet.placed()[instance] != node, 30, f"{instance} to leave {node}")
        fleet.converge()
        assert f"measured RTT 45 ms from fetch-2 to {node} > max_latency 20 ms" in fleet.log()
    finally:
        fleet.core.patch_node("fetch-2", {"metadata": {"annotations": {RTT: None}}})


def test_a_pod_that_keeps_failing_moves_to_another_node(fleet):
    instance = "pick-and-place-motion-planner-fetch-1"
    node = fleet.placed()[instance]
    pod = next(p for p in fleet.pods()[instance] if not p.metadata.deletion_timestamp)
    statuses = [
        {
            "name": c.name, "ready": False, "restartCount": 5, "image": c.image, "imageID": "", "started": False,
            "state": {"waiting": {"reason": "CrashLoopBackOff", "message": "back-off restarting failed container"}},
        }
        for c in pod.spec.containers
    ]  # fmt: skip
    fleet.core.patch_namespaced_pod_status(pod.metadata.name, NAMESPACE, {"status": {"containerStatuses": statuses}})
    wait_for(lambda: fleet.placed()[instance] != node, 30, f"{instance} to leave {node}")
    fleet.converge()
    assert "keeps failing" in fleet.log()


def test_the_leader_killed_between_record_write_and_apply_another_replica_finishes_the_move(fleet, tmp_path):
    """Both replicas carry a failpoint that kills the first of them to write a record, right after the write and
    before the apply: the leader dies there; the other takes the Lease once it expires and finishes the move."""
    assert fleet.controller("stopped").returncode == 0
    try:
        restarted = fleet.controller(env={"KUBEROS_CONTROLLER_FAILPOINT": f"after-record-once:{tmp_path / 'fired'}"})
        assert restarted.returncode == 0, restarted.stdout[-3000:]
        first = fleet.leader_pid()
        node, leaving = fleet.busiest_edge()
        fleet.node_down(node)
        try:
            wait_for(lambda: first not in fleet.pids(), 30, "the leader to die at the failpoint")
            assert "failpoint after-record" in fleet.log()
            # The record says where modules go, but the leader applied nothing: the old pods are still on the dead node.
            assert node not in fleet.placed().values()
            assert any(p.spec.node_name == node for i in leaving for p in fleet.pods().get(i, []))
            second = fleet.leader_pid()
            assert second != first and len(fleet.pids()) == 1
            fleet.converge()
            assert fleet.pids() == [second]
        finally:
            fleet.node_up(node)
        fleet.converge()
    finally:
        assert fleet.controller("stopped").returncode == 0  # the survivor was started with the failpoint set
        assert fleet.controller().returncode == 0


def test_the_controller_survives_an_api_server_restart(fleet):
    with open(os.path.join(fleet.cluster.state_dir, "run", "kube-apiserver.pid"), encoding="utf-8") as handle:
        os.kill(int(handle.read()), signal.SIGKILL)
    time.sleep(2)
    restarted = fleet.cluster.start()
    assert restarted.returncode == 0, restarted.stdout[-3000:]
    assert len(fleet.pids()) == 2, "both replicas kept running"
    node, _ = fleet.busiest_edge()
    fleet.node_down(node)
    try:
        fleet.converge(timeout=90)
        assert node not in fleet.placed().values()
    finally:
        fleet.node_up(node)
    assert "relisting" in fleet.log(), "the watches noticed the restart and listed again"
    fleet.converge()


def test_reconcile_playbook_does_one_pass_and_check_mode_changes_nothing(fleet):
    assert fleet.controller("stopped").returncode == 0
    try:
        node, leaving = fleet.busiest_edge()
        before = fleet.placed()
        fleet.node_down(node)
        try:
            time.sleep(GRACE + 1)
            kube = ("-e", f"kuberos_kubeconfig={fleet.cluster.kubeconfig}", "-e", f"kuberos_reconcile_grace={GRACE}")
            checked = playbook("reconcile.yml", *kube, "--check")
            assert checked.returncode == 0, checked.stdout[-3000:]
            assert all(f"moved {i}: {node} ->" in checked.stdout for i in leaving), checked.stdout[-3000:]
            assert fleet.placed() == before, "check mode writes nothing"
            done = playbook("reconcile.yml", *kube)
            assert done.returncode == 0 and done.changed == 1, done.stdout[-3000:]
            fleet.converge()
            assert node not in fleet.placed().values()
        finally:
            fleet.node_up(node)
    finally:
        assert fleet.controller().returncode == 0


def test_the_record_holds_the_inventory_deploy_placed_with(fleet):
    """The controller re-places with the fleet model deploy used, read back from the cluster."""
    assert fleet.record().inventory_raw == inventory_raw()


FORBIDDEN = [
    ("get", "", "secrets", "kuberos-test-fleet"),
    ("list", "", "secrets", ""),
    ("patch", "", "nodes", ""),
    ("delete", "", "nodes", ""),
    ("create", "", "pods", "default"),
    ("create", "apps", "deployments", "default"),
    ("delete", "apps", "deployments", "kube-system"),
    ("patch", "", "configmaps", "kube-system"),
    ("delete", "", "pods", "kube-system"),
    ("patch", "apps", "deployments", "default"),
    ("create", "", "pods/exec", "kuberos-test-fleet"),
    ("get", "", "pods/log", "kube-system"),
    ("patch", "", "nodes/status", ""),
    ("update", "coordination.k8s.io", "leases", "kube-system"),
    ("update", "coordination.k8s.io", "leases", "kube-node-lease"),
    ("delete", "coordination.k8s.io", "leases", "kuberos-system"),
]
ALLOWED = [
    ("get", "coordination.k8s.io", "leases", "kuberos-system"),
    ("update", "coordination.k8s.io", "leases", "kuberos-system"),
    ("create", "coordination.k8s.io", "leases", "kuberos-system"),
    ("watch", "", "nodes", ""),
    ("list", "", "pods", ""),
    ("watch", "apps", "deployments", ""),
    ("patch", "apps", "deployments", "kuberos-test-fleet"),
    ("create", "apps", "deployments", "kuberos-test-fleet"),  # instances added by scaling (docs/scaling.md)
    ("delete", "apps", "deployments", "kuberos-test-fleet"),  # drained instances removed
    ("list", "metrics.k8s.io", "pods", "kuberos-test-fleet"),  # the cpu signal
    ("delete", "", "pods", "kuberos-test-fleet"),
    ("get", "", "pods/log", "kuberos-test-fleet"),  # the dashboard's last lines of each instance
    ("create", "", "pods", "kuberos-test-fleet"),  # the live graph check's pod (--graph-every)
    ("create", "", "configmaps", "kuberos-test-fleet"),
    ("create", "", "events", "kuberos-test-fleet"),
    ("watch", "", "events", ""),  # the dashboard's timeline
    ("create", "authentication.k8s.io", "tokenreviews", ""),  # the dashboard's access control
    ("create", "authorization.k8s.io", "subjectaccessreviews", ""),
]


def test_the_in_cluster_rights_are_enough_for_a_move_and_no_more(fleet, tmp_path):
    """The role's in-cluster objects applied; the controller then runs with the ServiceAccount's token only."""
    import subprocess
    import sys

    import yaml
    from kubernetes import client

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.manifests import NAME

    def in_cluster(state):
        settings = {
            "controller_mode": "in_cluster", "controller_state": state, "controller_kubeconfig": fleet.cluster.kubeconfig,
            "controller_image": "registry.invalid/kuberos-controller:test", "controller_fleets": ["test-fleet"],
        }  # fmt: skip
        return playbook("controller.yml", "-e", json.dumps(settings))

    applied = in_cluster("started")
    assert applied.returncode == 0, applied.stdout[-3000:]
    subject = f"system:serviceaccount:kuberos-system:{NAME}"
    authz = client.AuthorizationV1Api(fleet.core.api_client)

    def allowed(verb, group, resource, namespace) -> bool:
        sub = [*resource.split("/"), ""]
        attributes = {"verb": verb, "group": group, "resource": sub[0], "subresource": sub[1], "namespace": namespace}
        review = {"spec": {"user": subject, "groups": ["system:serviceaccounts"], "resourceAttributes": attributes}}
        return authz.create_subject_access_review(review).status.allowed

    assert [a for a in ALLOWED if not allowed(*a)] == []
    assert [f for f in FORBIDDEN if allowed(*f)] == []

    token = fleet.core.create_namespaced_service_account_token(NAME, "kuberos-system", {"spec": {"expirationSeconds": 3600}})
    with open(fleet.cluster.kubeconfig, encoding="utf-8") as handle:
        admin = yaml.safe_load(handle)
    admin["users"] = [{"name": NAME, "user": {"token": token.status.token}}]
    admin["contexts"][0]["context"]["user"] = NAME
    kubeconfig = tmp_path / "sa.kubeconfig"
    kubeconfig.write_text(yaml.safe_dump(admin))

    assert fleet.controller("stopped").returncode == 0
    log = tmp_path / "sa-controller.log"
    entry = "ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p.endswith(".collections"))}
    with open(log, "wb") as out:
        process = subprocess.Popen(
            [sys.executable, "-m", entry, "--kubeconfig", str(kubeconfig), "--grace", str(GRACE),
             "--dashboard-port", str(fleet.dashboard_port)],
            stdout=out, stderr=subprocess.STDOUT, env=env,
        )  # fmt: skip
    node, leaving = fleet.busiest_edge()
    try:
        wait_for(lambda: "controller started" in log.read_text(), 30, "the controller with the ServiceAccount's token")
        time.sleep(1)
        fleet.node_down(node)
        fleet.converge()
        assert node not in fleet.placed().values()
        rows = {r["instance"]: r for r in fleet.status()["rows"]}
        assert all(rows[i]["last_move"].get("from") == node for i in leaving), "it wrote the status"
        with urllib.request.urlopen(fleet.dashboard(1) + "api/events?q=ModuleMoved", timeout=10) as response:
            assert json.loads(response.read())["total"] >= len(leaving), "its dashboard reads the Events it wrote"
    finally:
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=20)
        fleet.node_up(node)
        removed = in_cluster("stopped")
        assert fleet.controller().returncode == 0
    text = log.read_text()
    assert not re.search(r"\b403\b", text) and "Forbidden" not in text, text[-3000:]  # (not a port such as 35403)
    assert "moved from" in text
    assert removed.returncode == 0, removed.stdout[-3000:]


def test_deploying_again_while_a_node_is_down_places_nothing_there(fleet, tmp_path):
    """A deploy with an unchanged spec while a node is down: the deploy leaves that node out."""
    assert fleet.controller("stopped").returncode == 0
    node, _ = fleet.busiest_edge()
    fleet.node_down(node)
    try:
        deployed = fleet.cluster.deploy(SPEC, tmp_path / "render")
        assert deployed.returncode == 0, deployed.stdout[-4000:]
        assert node not in fleet.placed().values()
        fleet.converge()
    finally:
        fleet.node_up(node)
        assert fleet.controller().returncode == 0


# -- the redundant controller ----------------------------------------------------------------------
def test_two_replicas_run_and_exactly_one_leads(fleet):
    assert len(fleet.pids()) == 2
    leader = fleet.leader_pid()
    assert f"{socket.gethostname()}_{leader} is the leader" in fleet.log()
    follower = next(p for p in fleet.pids() if p != leader)
    assert f"{socket.gethostname()}_{follower} is the leader" not in fleet.log(), "the follower never acted as leader"


def test_the_leader_killed_while_a_node_is_failing_hands_over_and_the_new_leader_moves(fleet):
    first = fleet.leader_pid()
    node, leaving = fleet.busiest_edge()
    before = fleet.moved_by()
    fleet.node_down(node)
    os.kill(first, signal.SIGKILL)  # inside the grace period: the dead leader has moved nothing yet
    try:
        # The record names the failed node until the new leader moves its modules: "running where the record says"
        # alone can hold before the node's failure is even seen, so wait for the move itself (same bound).
        wait_for(lambda: node not in fleet.placed().values(), 90, f"the new leader moving the modules off {node}")
        fleet.converge(timeout=90)
        second = fleet.leader_pid()
        assert second != first
        assert node not in fleet.placed().values()
        wait_for(lambda: all(fleet.moved_by().get(i, set()) - before.get(i, set()) for i in leaving), 20, "the move Events")
        now = fleet.moved_by()
        movers = set().union(*(now[i] - before.get(i, set()) for i in leaving))
        assert movers == {f"{socket.gethostname()}_{second}"}, "only the new leader moved the modules"
    finally:
        fleet.node_up(node)
        assert fleet.controller().returncode == 0  # the role starts the missing replica again
    assert len(fleet.pids()) == 2
    fleet.converge()


def test_a_paused_leader_stops_acting_before_its_lease_can_be_taken(fleet):
    """A leader frozen past its Lease (SIGSTOP: what a long pause or a partition from the API server looks like
    to the others) wakes up with a fault it was about to act on, and does nothing: the new leader acted."""
    first = fleet.leader_pid()
    identity = f"{socket.gethostname()}_{first}"
    node, leaving = fleet.busiest_edge()
    before = fleet.moved_by()
    fleet.node_down(node)
    os.kill(first, signal.SIGSTOP)
    try:
        wait_for(lambda: fleet.leader() not in ("", identity), 60, "another replica to take the Lease of the frozen one")
        second = fleet.leader_pid()
        assert second != first
        fleet.converge(timeout=90)
        assert node not in fleet.placed().values()
        os.kill(first, signal.SIGCONT)
        wait_for(lambda: f"{identity} is not the leader" in fleet.log(), 20, "the woken replica to see it does not lead")
        time.sleep(GRACE + 2)  # its grace timer for the failed node ran out while it was frozen
        now = fleet.moved_by()
        assert all(identity not in now.get(i, set()) - before.get(i, set()) for i in leaving), "the paused leader moved nothing"
        assert fleet.leader_pid() == second
        fleet.converge()
    finally:
        os.kill(first, signal.SIGCONT)
        fleet.node_up(node)
    fleet.converge()


def test_a_leader_whose_own_node_is_not_ready_hands_over_at_once(fleet, tmp_path):
    """Replicas told the node they run on (in a cluster: the pod's node, from the downward API)."""
    assert fleet.controller("stopped").returncode == 0
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p.endswith(".collections"))}
    processes = []

    def replica(node_name):
        command = [sys.executable, "-m", ENTRY, "--kubeconfig", fleet.cluster.kubeconfig, "--grace", str(GRACE)]
        with open(tmp_path / f"on-{node_name}.log", "wb") as out:
            process = subprocess.Popen([*command, "--node-name", node_name], stdout=out, stderr=subprocess.STDOUT, env=env)
        processes.append(process)
        return f"{socket.gethostname()}_{process.pid}"

    node, _ = fleet.busiest_edge()
    other = next(n for n in ("edge-1", "edge-2", "edge-3") if n != node)
    try:
        first = replica(node)
        wait_for(lambda: fleet.leader() == first, 30, "the replica on the busiest edge node to lead")
        second = replica(other)
        wait_for(lambda: "controller started" in (tmp_path / f"on-{other}.log").read_text(), 30, "the second replica")
        time.sleep(1)
        down_at = time.monotonic()
        fleet.node_down(node)
        wait_for(lambda: fleet.leader() == second, 30, "the healthy replica to take the Lease")
        handover = time.monotonic() - down_at
        assert "own node is NotReady" in (tmp_path / f"on-{node}.log").read_text()
        # Released, not expired: the healthy replica did not wait out the Lease (6 s after the last renewal).
        assert handover < 5.5, f"handover took {handover:.1f} s"
        fleet.converge()
        assert node not in fleet.placed().values()
    finally:
        for process in processes:
            process.send_signal(signal.SIGTERM)
        for process in processes:
            process.wait(timeout=30)
        fleet.node_up(node)
        assert fleet.controller().returncode == 0
    fleet.converge()
