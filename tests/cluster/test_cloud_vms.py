"""playbooks/cloud.yml against moto's server (the real EC2 API, started here) through amazon.aws, and the local cluster.

Proves: two VMs are launched with the right type, image and tags and written to the inventory (which the next run
reads as cloud nodes of the fleet); a rerun changes nothing; a request beyond the budget launches only what fits and
says why, or nothing with cloud_vms_fail_on_refusal; release terminates the VMs and takes them out of the inventory;
check mode launches nothing; a refusal of the emulator, or a failure after launching, leaves the fleet as it was
(nothing running, no inventory entry, no node) with the error shown; credentials never appear in the output; on the
local cluster provisioned VMs are Ready kwok nodes labelled as cloud nodes, and a released VM's node is drained
(its pods evicted) and gone.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
import uuid

import pytest
import yaml
from helpers import ROOT, MotoServer, playbook

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.ansible_inventory import read_inventory

ACCESS_KEY = "AKIAKUBEROSTEST4EXAMPLE"
SECRET_KEY = f"secret-{uuid.uuid4().hex}"
SESSION_TOKEN = f"token-{uuid.uuid4().hex}"
FLEET = "test-fleet"
SITE = "local"
BUDGET = {
    "max_vms": 3,
    "instance_types": {
        "t3.large": {"cpu": 2, "memory": "8Gi", "hourly_price": 0.0832},
        "g4dn.xlarge": {"cpu": 4, "memory": "16Gi", "gpu": 1, "hourly_price": 0.526, "max": 1},
    },
}


def vm_name(number: int, fleet: str = FLEET) -> str:
    return f"{SITE}-{fleet}-cloud-{number}"


@pytest.fixture(scope="module")
def moto(tmp_path_factory):
    server = MotoServer(tmp_path_factory.mktemp("moto") / "moto.log").start()
    try:
        server.image_id = server.ec2().describe_images()["Images"][0]["ImageId"]
        yield server
    finally:
        server.stop()


@pytest.fixture
def cloud(moto, tmp_path, monkeypatch):
    """A fresh emulator, dummy credentials in the environment (as a user would export them), and a copy of the
    embedded inventory whose directory gets cloud_vms.yml (the role's default place)."""
    moto.reset()
    for name in ("AWS_PROFILE", "AWS_DEFAULT_PROFILE", "AWS_CONFIG_FILE", "AWS_SHARED_CREDENTIALS_FILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", ACCESS_KEY)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", SECRET_KEY)
    monkeypatch.setenv("AWS_SESSION_TOKEN", SESSION_TOKEN)
    inventory = tmp_path / "site"
    shutil.copytree(os.path.join(ROOT, "inventories", "local"), inventory)
    return Cloud(moto, inventory)


class Cloud:
    def __init__(self, moto: MotoServer, inventory):
        self.moto = moto
        self.inventory = inventory
        self.file = inventory / "cloud_vms.yml"

    def run(self, *extra, join="none", **variables):
        settings = {
            "cloud_vms_fleet": FLEET, "cloud_vms_site": SITE, "cloud_vms_budget": BUDGET,
            "cloud_vms_endpoint_url": self.moto.url, "cloud_vms_region": self.moto.REGION,
            "cloud_vms_image_id": self.moto.image_id, "cloud_vms_join": join, "cloud_vms_wait_timeout": 60,
            **variables,
        }  # fmt: skip
        return playbook("cloud.yml", "-e", json.dumps(settings), *extra, inventory=self.inventory, timeout=600)

    def instances(self, *states):
        """name -> instance of every instance in the emulator (in the given states; default: not terminated)."""
        states = states or ("pending", "running", "stopping", "stopped")
        reservations = self.moto.ec2().describe_instances(Filters=[{"Name": "instance-state-name", "Values": list(states)}])
        found = {}
        for reservation in reservations["Reservations"]:
            for item in reservation["Instances"]:
                tags = {t["Key"]: t["Value"] for t in item.get("Tags", [])}
                found[tags.get("Name", item["InstanceId"])] = {**item, "tags": tags}
        return found

    def hosts(self) -> dict:
        if not self.file.exists():
            return {}
        document = yaml.safe_load(self.file.read_text()) or {}
        return document["all"]["children"]["cloud"]["hosts"] or {}


def ok(result):
    return result.returncode == 0, result.stdout[-6000:] + result.stderr[-3000:]


pytestmark = pytest.mark.playbook


def test_two_vms_are_launched_tagged_written_to_the_inventory_and_a_rerun_changes_nothing(cloud):
    first = cloud.run(cloud_vms_count=2)
    assert ok(first)[0], ok(first)[1]
    assert first.changed >= 2
    running = cloud.instances()
    assert sorted(running) == [vm_name(1), vm_name(2)]
    for name, item in running.items():
        assert item["State"]["Name"] == "running"
        assert item["InstanceType"] == "t3.large" and item["ImageId"] == cloud.moto.image_id
        assert {k: item["tags"][k] for k in ("kuberos.io/managed-by", "kuberos.io/site", "kuberos.io/fleet")} == {
            "kuberos.io/managed-by": "kuberos", "kuberos.io/site": SITE, "kuberos.io/fleet": FLEET,
        }  # fmt: skip
        assert item["tags"]["kuberos.io/inventory-host"] == name
        assert (item["tags"]["kuberos.io/cpu"], item["tags"]["kuberos.io/memory"]) == ("2", "8Gi")
    hosts = cloud.hosts()
    assert sorted(hosts) == [vm_name(1), vm_name(2)]
    assert hosts[vm_name(1)]["kuberos_cloud_instance_id"] == running[vm_name(1)]["InstanceId"]
    assert hosts[vm_name(1)]["ansible_host"] == running[vm_name(1)]["PublicIpAddress"]
    # The next run reads the file as part of the inventory: the VMs are cloud nodes of the fleet, with their capacity.
    model = load_inventory(read_inventory(str(cloud.inventory)))
    node = model.nodes[vm_name(2)]
    assert (node.tier, node.cpu_millis, node.memory_bytes, node.fleets, node.shared, node.latency_ms) == (
        "cloud", 2000, 8 * 1024**3, (FLEET,), False, 50.0
    )  # fmt: skip
    assert "cloud-1" in model.nodes  # the site's own cloud VMs are still there

    text = cloud.file.read_text()
    again = cloud.run(cloud_vms_count=2)
    assert ok(again)[0], ok(again)[1]
    assert again.changed == 0, again.stdout[-4000:]
    assert {n: i["InstanceId"] for n, i in cloud.instances().items()} == {n: i["InstanceId"] for n, i in running.items()}
    assert cloud.file.read_text() == text


def test_a_request_beyond_the_budget_launches_what_fits_and_says_why(cloud, monkeypatch):
    other = cloud.run(cloud_vms_count=1, cloud_vms_fleet="warehouse-fleet")
    assert ok(other)[0], ok(other)[1]
    result = cloud.run(cloud_vms_count=5)
    assert ok(result)[0], ok(result)[1]
    assert sorted(cloud.instances()) == [vm_name(1), vm_name(2), vm_name(1, "warehouse-fleet")]
    assert "refused to launch 3 t3.large: the budget allows at most 3 VM(s) at site local, and 3 run there" in " ".join(
        result.stdout.split()
    )
    assert sorted(cloud.hosts()) == [vm_name(1), vm_name(2), vm_name(1, "warehouse-fleet")]

    # What a caller such as the controller reads: the run's custom stats, through the json callback.
    monkeypatch.setenv("ANSIBLE_STDOUT_CALLBACK", "json")
    monkeypatch.setenv("ANSIBLE_SHOW_CUSTOM_STATS", "true")
    gpu = cloud.run(cloud_vms_count=4, cloud_vms_fleet="warehouse-fleet", cloud_vms_instance_type="g4dn.xlarge")
    assert gpu.returncode == 0, gpu.stdout[-4000:] + gpu.stderr[-2000:]
    assert len(cloud.instances()) == 3  # the site is full: nothing more, whatever the type
    stats = json.loads(gpu.stdout)["global_custom_stats"]["cloud_vms"]
    assert (stats["fleet"], stats["launched"], stats["released"], stats["kept"]) == (
        "warehouse-fleet", [], [], [vm_name(1, "warehouse-fleet")]
    )  # fmt: skip
    assert [(r["count"], r["instance_type"], r["reason"]) for r in stats["refused"]] == [
        (3, "g4dn.xlarge", "the budget allows at most 3 VM(s) at site local, and 3 run there")
    ]


def test_with_fail_on_refusal_a_request_beyond_the_budget_launches_nothing(cloud):
    result = cloud.run(cloud_vms_count=2, cloud_vms_instance_type="g4dn.xlarge", cloud_vms_fail_on_refusal=True)
    assert result.returncode != 0
    assert "refused to launch 1 g4dn.xlarge: the budget allows at most 1 VM(s) of type g4dn.xlarge" in " ".join(
        result.stdout.split()
    )
    assert cloud.instances() == {} and not cloud.file.exists()


def test_release_terminates_the_vms_and_takes_them_out_of_the_inventory(cloud):
    assert ok(cloud.run(cloud_vms_count=3))[0]
    launched = cloud.instances()
    by_name = cloud.run(cloud_vms_count=2, cloud_vms_release=[vm_name(1)])
    assert ok(by_name)[0], ok(by_name)[1]
    assert sorted(cloud.instances()) == [vm_name(2), vm_name(3)]
    assert sorted(cloud.hosts()) == [vm_name(2), vm_name(3)]
    assert launched[vm_name(1)]["InstanceId"] in {i["InstanceId"] for i in cloud.instances("terminated").values()}

    fewer = cloud.run(cloud_vms_count=1)
    assert ok(fewer)[0], ok(fewer)[1]
    assert sorted(cloud.instances()) == [vm_name(2)]  # the newest went first

    gone = cloud.run(cloud_vms_state="absent")
    assert ok(gone)[0], ok(gone)[1]
    assert gone.changed >= 1
    assert cloud.instances() == {} and cloud.hosts() == {}
    assert len(cloud.instances("terminated")) == 3
    assert cloud.run(cloud_vms_state="absent").changed == 0


def test_check_mode_launches_nothing_and_says_what_it_would_do(cloud):
    result = cloud.run("--check", cloud_vms_count=2)
    assert ok(result)[0], ok(result)[1]
    assert result.changed == 1  # the plan, reported as the change a real run would make
    assert f"Check mode, would: site local, fleet test-fleet: 2 VM(s) wanted, 0 kept; launch 2 t3.large ({vm_name(1)}, " in (
        " ".join(result.stdout.split())
    )
    assert cloud.instances() == {} and not cloud.file.exists()
    assert ok(cloud.run(cloud_vms_count=1))[0]
    release = cloud.run("--check", cloud_vms_state="absent")
    assert ok(release)[0]
    assert f"0 VM(s) wanted, 0 kept; release 1 ({vm_name(1)})" in " ".join(release.stdout.split())
    assert sorted(cloud.instances()) == [vm_name(1)]


@pytest.mark.parametrize(
    ("variables", "error"),
    [
        ({"cloud_vms_image_id": "ami-00000000deadbeef"}, "InvalidAMIID.NotFound"),
        ({"cloud_vms_budget": {"max_vms": 5, "instance_types": {"t9.mega": {"cpu": 2, "memory": "4Gi"}}},
          "cloud_vms_instance_type": "t9.mega"}, "InvalidInstanceType.NotFound"),
        ({"cloud_vms_subnet_id": "subnet-0000000000000dead"}, "InvalidSubnetID.NotFound"),
    ],
    ids=["unknown-image", "unknown-instance-type", "unknown-subnet"],
)  # fmt: skip
def test_the_emulator_refusing_leaves_the_fleet_as_it_was(cloud, variables, error):
    assert ok(cloud.run(cloud_vms_count=1))[0]
    before, text = cloud.instances(), cloud.file.read_text()
    result = cloud.run(cloud_vms_count=3, **variables)
    assert result.returncode != 0
    assert error in result.stdout, result.stdout[-4000:]
    assert "were terminated and their nodes removed" in " ".join(result.stdout.split())
    assert {n: i["InstanceId"] for n, i in cloud.instances().items()} == {n: i["InstanceId"] for n, i in before.items()}
    assert cloud.file.read_text() == text


def test_a_failure_after_launching_terminates_what_was_launched(cloud, tmp_path):
    """The VMs run, then their nodes cannot be made (no cluster at that kubeconfig): the run takes them back."""
    assert ok(cloud.run(cloud_vms_count=1))[0]
    text = cloud.file.read_text()
    result = cloud.run(cloud_vms_count=3, join="simulated", cloud_vms_kubeconfig=str(tmp_path / "no-such-kubeconfig"))
    assert result.returncode != 0
    words = " ".join(result.stdout.split())
    assert f"the VMs launched by this run ({vm_name(2)}, {vm_name(3)}) were terminated" in words, words[-3000:]
    assert sorted(cloud.instances()) == [vm_name(1)]
    assert sorted(cloud.instances("terminated")) == [vm_name(2), vm_name(3)]
    assert cloud.file.read_text() == text


def test_bad_settings_fail_before_the_cloud_is_asked(cloud):
    result = cloud.run(cloud_vms_count=-1, cloud_vms_instance_type="t3.larg")
    assert result.returncode != 0
    words = " ".join(result.stdout.split())
    assert "the cloud VM settings are not valid (2 problems)" in words
    assert "cloud_vms: cloud_vms_count: -1 (int) is not valid; expected a whole number >= 0" in words
    assert "cloud_vms_instance_type: 't3.larg' is not an instance type of cloud_vms_budget" in words
    assert "Find the site's VMs" not in result.stdout
    assert cloud.instances() == {}


def test_credentials_never_appear_in_the_output(cloud, monkeypatch):
    from_env = cloud.run("-v", cloud_vms_count=1)
    assert ok(from_env)[0], ok(from_env)[1]
    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(name)
    secret, token = f"secret-{uuid.uuid4().hex}", f"token-{uuid.uuid4().hex}"
    given = cloud.run(
        "-vvv", cloud_vms_count=2, cloud_vms_access_key=ACCESS_KEY, cloud_vms_secret_key=secret, cloud_vms_session_token=token
    )
    assert ok(given)[0], ok(given)[1]
    assert sorted(cloud.instances()) == [vm_name(1), vm_name(2)]  # the variables were used: the emulator was reached
    failed = cloud.run("-vvv", cloud_vms_count=3, cloud_vms_image_id="ami-00000000deadbeef", cloud_vms_secret_key=secret)
    assert failed.returncode != 0
    for result in (from_env, given, failed):
        output = result.stdout + result.stderr
        assert SECRET_KEY not in output and SESSION_TOKEN not in output
        assert secret not in output and token not in output
    # The access key id is not a secret to amazon.aws (its modules show it at -vvv, never at -v or less).
    assert ACCESS_KEY not in from_env.stdout + from_env.stderr


# ---------------------------------------------------------------------------------------------- the local cluster
def wait_for(predicate, timeout, what):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.5)
    raise AssertionError(f"not within {timeout} s: {what}")


@pytest.mark.cluster
def test_provisioned_vms_are_ready_cloud_nodes_and_a_released_vms_node_is_drained_and_gone(cloud, cluster):
    from kubernetes import client

    core, apps, _discovery = cluster.clients()
    namespace = "cloud-vms-test"
    try:
        first = cloud.run(cloud_vms_count=2, join="simulated", cloud_vms_kubeconfig=cluster.kubeconfig)
        assert ok(first)[0], ok(first)[1]
        for name in (vm_name(1), vm_name(2)):
            node = core.read_node(name)
            assert {c.type: c.status for c in node.status.conditions}["Ready"] == "True"
            labels = node.metadata.labels
            assert labels["kuberos.io/role"] == "cloud" and labels["kuberos.io/shared"] == "false"
            assert labels[f"fleet-access.kuberos.io/{FLEET}"] == "true"
            assert labels["resource-group.kuberos.io/name"] == "cloud-eu-central-1"
            assert node.status.capacity["cpu"] == "2" and node.status.capacity["memory"] == "8Gi"
        again = cloud.run(cloud_vms_count=2, join="simulated", cloud_vms_kubeconfig=cluster.kubeconfig)
        assert ok(again)[0] and again.changed == 0, again.stdout[-4000:]

        # A module pinned to the VM that goes next (the newest): its pod runs there until the release drains the node.
        core.create_namespace(client.V1Namespace(metadata=client.V1ObjectMeta(name=namespace)))
        labels = {"app": "pinned", "app.kubernetes.io/managed-by": "kuberos"}
        pod_spec = client.V1PodSpec(
            node_selector={"device.kuberos.io/hostname": vm_name(2)},
            containers=[client.V1Container(name="planner", image="registry/planner:1.0")],
        )
        apps.create_namespaced_deployment(
            namespace,
            client.V1Deployment(
                metadata=client.V1ObjectMeta(name="pinned"),
                spec=client.V1DeploymentSpec(
                    replicas=1,
                    selector=client.V1LabelSelector(match_labels=labels),
                    template=client.V1PodTemplateSpec(metadata=client.V1ObjectMeta(labels=labels), spec=pod_spec),
                ),
            ),
        )

        def pods():
            return [p for p in core.list_namespaced_pod(namespace).items if not p.metadata.deletion_timestamp]

        def running_on_vm():
            return [p for p in pods() if p.spec.node_name == vm_name(2) and p.status.phase == "Running"]

        (pinned,) = wait_for(running_on_vm, 60, f"the pinned pod Running on {vm_name(2)}")

        fewer = cloud.run(cloud_vms_count=1, join="simulated", cloud_vms_kubeconfig=cluster.kubeconfig)
        assert ok(fewer)[0], ok(fewer)[1]
        drained = rf"Cordon each node and evict its pods\] \*+\nchanged: \[localhost\] => \(item={vm_name(2)}\)"
        assert re.search(drained, fewer.stdout), fewer.stdout[-4000:]
        assert [n.metadata.name for n in core.list_node().items if n.metadata.name.startswith(f"{SITE}-")] == [vm_name(1)]
        assert sorted(cloud.instances()) == [vm_name(1)]
        assert pinned.metadata.name not in {p.metadata.name for p in pods()}  # evicted
        replacement = wait_for(pods, 30, "the Deployment's replacement pod")
        assert all(p.spec.node_name in (None, "") and p.status.phase == "Pending" for p in replacement)  # for the controller
    finally:
        if namespace in {n.metadata.name for n in core.list_namespace().items}:
            core.delete_namespace(namespace)
        gone = cloud.run(cloud_vms_state="absent", join="simulated", cloud_vms_kubeconfig=cluster.kubeconfig)
    assert ok(gone)[0], ok(gone)[1]
    assert not [n for n in core.list_node().items if n.metadata.name.startswith(f"{SITE}-{FLEET}-cloud-")]
    assert cloud.instances() == {}
