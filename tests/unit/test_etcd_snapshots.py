"""The stacked etcd's pure rules (kuberos_cluster/etcd_snapshots.py) and their filters: members as kubeadm names them,
--initial-cluster, snapshot names and retention, etcdutl's status, the backup's source and each control plane's part of
a restore. The restore's commands run for real against three etcd members in tests/integration/test_etcd_restore.py."""

from __future__ import annotations

import pytest
from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.filter.etcd_backup_source import etcd_backup_source
from ansible_collections.kuberos.platform.plugins.filter.etcd_members import etcd_members
from ansible_collections.kuberos.platform.plugins.filter.etcd_restore_plan import etcd_restore_plan
from ansible_collections.kuberos.platform.plugins.filter.etcd_snapshot_status import etcd_snapshot_status
from ansible_collections.kuberos.platform.plugins.filter.etcd_snapshots_to_remove import etcd_snapshots_to_remove
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import etcd_snapshots as es

# The sample site's control planes: inventory names differ from node names (kuberos_node_name).
CPS = ["edge-a.site.example.internal", "edge-b.site.example.internal", "edge-c.site.example.internal"]
HOSTVARS = {
    "edge-a.site.example.internal": {"kuberos_node_name": "edge-a", "kuberos_address": "10.215.0.11"},
    "edge-b.site.example.internal": {"kuberos_node_name": "edge-b", "ansible_host": "10.215.0.12"},
    "edge-c.site.example.internal": {"kuberos_node_name": "edge-c", "kuberos_address": "10.215.0.13", "ansible_host": "x"},
}
# What etcdutl v3.5.35 printed for a snapshot of a three-member cluster (tests/integration/test_etcd_restore.py).
STATUS = '{"hash":2508559452,"revision":52,"totalKey":59,"totalSize":40960}\n'


def manifest(
    name="edge-a",
    peer="https://10.215.0.11:2380",
    data_dir="/var/lib/etcd",
    host_path=None,
    image="registry.k8s.io/etcd:3.5.35-0",
):
    """kubeadm's etcd.yaml, parsed, as far as the restore reads it."""
    command = ["etcd", "--advertise-client-urls=https://10.215.0.11:2379", f"--data-dir={data_dir}", f"--name={name}",
               f"--initial-advertise-peer-urls={peer}", "--initial-cluster=edge-a=https://10.215.0.11:2380"]  # fmt: skip
    return {
        "apiVersion": "v1",
        "kind": "Pod",
        "spec": {
            "containers": [{"name": "etcd", "image": image, "command": command}],
            "volumes": [
                {"name": "etcd-certs", "hostPath": {"path": "/etc/kubernetes/pki/etcd", "type": "DirectoryOrCreate"}},
                {"name": "etcd-data", "hostPath": {"path": host_path or data_dir, "type": "DirectoryOrCreate"}},
            ],
        },
    }


def test_members_are_named_after_their_nodes_and_advertise_the_api_servers_address():
    found = etcd_members(CPS, HOSTVARS)
    assert found["members"] == [
        {"host": CPS[0], "name": "edge-a", "address": "10.215.0.11", "peer_url": "https://10.215.0.11:2380"},
        {"host": CPS[1], "name": "edge-b", "address": "10.215.0.12", "peer_url": "https://10.215.0.12:2380"},
        {"host": CPS[2], "name": "edge-c", "address": "10.215.0.13", "peer_url": "https://10.215.0.13:2380"},
    ]
    assert found["initial_cluster"] == (
        "edge-a=https://10.215.0.11:2380,edge-b=https://10.215.0.12:2380,edge-c=https://10.215.0.13:2380"
    )
    # no kuberos_node_name: the inventory name; an IPv6 address in brackets, as kubeadm writes it
    single = etcd_members(["cp1"], {"cp1": {"kuberos_address": "fd00::11"}})
    assert single["initial_cluster"] == "cp1=https://[fd00::11]:2380"


@pytest.mark.parametrize(
    ("hostvars", "expected"),
    [
        ({"a": {"kuberos_node_name": "same", "kuberos_address": "10.0.0.1"},
          "b": {"kuberos_node_name": "same", "kuberos_address": "10.0.0.2"}}, ["hosts.b: has the node name same of a"]),
        ({"a": {"kuberos_address": "10.0.0.1"}, "b": {"kuberos_address": "10.0.0.1"}},
         ["hosts.b: has the peer URL https://10.0.0.1:2380 of a"]),
        ({"a": {"kuberos_node_name": "Edge_A", "kuberos_address": "10.0.0.1"}, "b": {"kuberos_address": "10.0.0.2"}},
         ["hosts.a.kuberos_node_name: 'Edge_A' is not a node name"]),
        ({"a": {"kuberos_address": "10.0.0.1,x"}, "b": {"kuberos_address": "10.0.0.2"}},
         ["hosts.a.kuberos_address: '10.0.0.1,x'"]),
    ],
)  # fmt: skip
def test_members_etcd_cannot_tell_apart_or_use_are_named_with_their_host(hostvars, expected):
    with pytest.raises(AnsibleFilterError) as raised:
        etcd_members(["a", "b"], hostvars)
    assert all(text in str(raised.value) for text in expected), str(raised.value)
    with pytest.raises(AnsibleFilterError, match=r"groups\.control_plane: is empty"):
        etcd_members([], {})


def test_snapshot_names_sort_by_time_and_name_their_node():
    assert es.snapshot_name("20261207T031500Z", "edge-a") == "etcd-snapshot-20261207T031500Z-edge-a.db"
    with pytest.raises(SpecError, match="not a UTC time"):
        es.snapshot_name("2026-12-07 03:15", "edge-a")
    with pytest.raises(SpecError, match="not a node name"):
        es.snapshot_name("20261207T031500Z", "../etc")


@pytest.mark.parametrize(
    ("names", "keep", "removed"),
    [
        ([], 7, []),
        (["etcd-snapshot-20261201T000000Z-edge-a.db"], 1, []),
        # the newest by the time in the name, whatever the order given or the node
        (["/b/etcd-snapshot-20261203T000000Z-edge-b.db", "/b/etcd-snapshot-20261201T000000Z-edge-a.db",
          "/b/etcd-snapshot-20261202T000000Z-edge-c.db"], 2, ["/b/etcd-snapshot-20261201T000000Z-edge-a.db"]),
        (["/b/etcd-snapshot-20261203T000000Z-edge-b.db", "/b/etcd-snapshot-20261201T000000Z-edge-a.db",
          "/b/etcd-snapshot-20261202T000000Z-edge-c.db"], 1,
         ["/b/etcd-snapshot-20261201T000000Z-edge-a.db", "/b/etcd-snapshot-20261202T000000Z-edge-c.db"]),
        # other files are never selected, however old they look
        (["/b/etcd-snapshot-20200101T000000Z-edge-a.db.part", "/b/notes.db", "/b/etcd-snapshot-old.db",
          "/b/etcd-snapshot-20261201T000000Z-edge-a.db"], 1, []),
    ],
)  # fmt: skip
def test_retention_keeps_the_newest_snapshots_and_nothing_else_is_touched(names, keep, removed):
    assert etcd_snapshots_to_remove(names, keep) == removed
    assert etcd_snapshots_to_remove(names, str(keep)) == removed  # -e etcd_backup_keep=2 arrives as text


@pytest.mark.parametrize("keep", [0, -1, True, "seven", None])
def test_retention_refuses_to_keep_nothing(keep):
    with pytest.raises(AnsibleFilterError, match="keep"):
        etcd_snapshots_to_remove(["etcd-snapshot-20261201T000000Z-edge-a.db"], keep)


def test_snapshot_status_reports_revision_keys_and_size():
    assert etcd_snapshot_status(STATUS) == {
        "hash": 2508559452, "revision": 52, "keys": 59, "size_bytes": 40960, "size": "40.0 KiB", "version": "",
    }  # fmt: skip
    # etcd 3.6 adds the storage version; a log line before the JSON is skipped
    newer = 'note\n{"hash":1,"revision":9,"totalKey":3,"totalSize":3145728,"version":"3.6.0"}'
    assert etcd_snapshot_status(newer)["size"] == "3.0 MiB" and etcd_snapshot_status(newer)["version"] == "3.6.0"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "not etcdutl's JSON status"),
        ("Error: snapshot file has no hash", "not etcdutl's JSON status"),
        ('{"hash":1,"revision":"52","totalKey":1,"totalSize":1}', "not etcdutl's JSON status"),
        ('{"hash":1,"revision":0,"totalKey":0,"totalSize":20480}', "holds no cluster"),
    ],
)
def test_an_unreadable_or_empty_snapshot_is_refused(text, message):
    with pytest.raises(AnsibleFilterError, match=message):
        etcd_snapshot_status(text)


def _pod(name, node, phase="Running", ready="True"):
    return {"metadata": {"name": name}, "spec": {"nodeName": node},
            "status": {"phase": phase, "conditions": [{"type": "Ready", "status": ready}]}}  # fmt: skip


def test_the_backup_takes_the_first_healthy_member_on_a_control_plane():
    pods = [_pod("etcd-edge-a", "edge-a", ready="False"), _pod("etcd-edge-b", "edge-b"), _pod("etcd-edge-c", "edge-c")]
    chosen = etcd_backup_source(pods, CPS, HOSTVARS, stamp="20261207T031500Z")
    assert chosen == {"pod": "etcd-edge-b", "node": "edge-b", "host": CPS[1], "name": "etcd-snapshot-20261207T031500Z-edge-b.db"}
    assert etcd_backup_source(pods, CPS, HOSTVARS, stamp="20261207T031500Z", preferred=CPS[2])["pod"] == "etcd-edge-c"


def test_no_healthy_member_names_every_pod_and_why():
    pods = [_pod("etcd-edge-a", "edge-a", phase="Pending"), _pod("etcd-edge-b", "edge-b", ready="False"), _pod("etcd-x", "x")]
    with pytest.raises(AnsibleFilterError) as raised:
        etcd_backup_source(pods, CPS, HOSTVARS, stamp="20261207T031500Z")
    text = str(raised.value)
    assert "kube-system/etcd-edge-a: it is Pending" in text and "kube-system/etcd-edge-b: it is not Ready" in text
    assert "kube-system/etcd-x: its node 'x' is not a control plane" in text
    with pytest.raises(AnsibleFilterError, match="no etcd static pod"):
        etcd_backup_source([], CPS, HOSTVARS, stamp="20261207T031500Z")
    with pytest.raises(AnsibleFilterError, match=f"{CPS[0]} runs no Running and Ready etcd pod"):
        etcd_backup_source([_pod("etcd-edge-a", "edge-a", ready="False"), _pod("etcd-edge-b", "edge-b")], CPS, HOSTVARS,
                           stamp="20261207T031500Z", preferred=CPS[0])  # fmt: skip


def test_a_restore_plan_rebuilds_the_member_the_manifest_describes():
    plan = etcd_restore_plan(CPS, HOSTVARS, CPS[1], manifest("edge-b", "https://10.215.0.12:2380"), "20261207T031500Z")
    cluster = "edge-a=https://10.215.0.11:2380,edge-b=https://10.215.0.12:2380,edge-c=https://10.215.0.13:2380"
    assert plan["snapshot"] == "/var/lib/etcd-restore-20261207T031500Z.db"
    assert plan["restored_dir"] == "/var/lib/etcd.restored-20261207T031500Z"
    assert plan["kept_dir"] == "/var/lib/etcd.before-restore-20261207T031500Z"
    assert plan["token"] == "kuberos-restore-20261207t031500z" and plan["initial_cluster"] == cluster
    assert plan["restore_argv"] == [
        "ctr", "--namespace", "k8s.io", "run", "--rm", "--mount", "type=bind,src=/var/lib,dst=/var/lib,options=rbind:rw",
        "registry.k8s.io/etcd:3.5.35-0", "kuberos-etcd-restore-20261207t031500z",
        "etcdutl", "snapshot", "restore", "/var/lib/etcd-restore-20261207T031500Z.db", "--name", "edge-b",
        "--initial-cluster", cluster, "--initial-cluster-token", "kuberos-restore-20261207t031500z",
        "--initial-advertise-peer-urls", "https://10.215.0.12:2380", "--data-dir", "/var/lib/etcd.restored-20261207T031500Z",
        "--bump-revision", "1000000000", "--mark-compacted",
    ]  # fmt: skip
    status = ["etcdutl", "snapshot", "status", "/var/lib/etcd-restore-20261207T031500Z.db", "-w", "json"]
    assert plan["status_argv"][-6:] == status
    assert plan["status_argv"][8] == "kuberos-etcd-status-20261207t031500z"  # its own container id
    # another data directory (a site's etcd.local.dataDir): the snapshot and the new directory beside it
    other = etcd_restore_plan(CPS, HOSTVARS, CPS[0], manifest(data_dir="/srv/etcd/data"), "20261207T031500Z", bump_revision="5")
    assert other["restored_dir"] == "/srv/etcd/data.restored-20261207T031500Z"
    assert "src=/srv/etcd,dst=/srv/etcd" in other["restore_argv"][6]
    assert other["restore_argv"][-3:] == ["--bump-revision", "5", "--mark-compacted"]


@pytest.mark.parametrize(
    ("host", "pod", "message"),
    [
        (CPS[0], manifest(name="edge-x"), "its etcd member is named 'edge-x', the inventory says 'edge-a'"),
        (CPS[0], manifest(peer="https://10.215.0.99:2380"), "advertises https://10.215.0.99:2380, the inventory says https://10.215.0.11:2380"),
        (CPS[0], manifest(host_path="/mnt/elsewhere"), "'/mnt/elsewhere' is not the data directory '/var/lib/etcd'"),
        (CPS[0], manifest(data_dir="/etcd"), "expected an absolute path two levels deep or more"),
        (CPS[0], {"spec": {"containers": [{"name": "kube-apiserver"}]}}, "has no container named etcd"),
        (CPS[0], {"spec": {"containers": [{"name": "etcd", "image": "e", "command": ["etcd"]}]}}, "has no --name"),
        ("edge-z", manifest(), "hosts.edge-z: is not one of the control planes"),
    ],
)  # fmt: skip
def test_a_restore_the_manifests_do_not_describe_is_refused(host, pod, message):
    with pytest.raises(AnsibleFilterError) as raised:
        etcd_restore_plan(CPS, HOSTVARS, host, pod, "20261207T031500Z")
    assert message in str(raised.value), str(raised.value)


def test_a_restore_needs_a_utc_time_and_a_positive_revision_bump():
    with pytest.raises(AnsibleFilterError, match="not a UTC time"):
        etcd_restore_plan(CPS, HOSTVARS, CPS[0], manifest(), "now")
    with pytest.raises(AnsibleFilterError, match="expected a positive number"):
        etcd_restore_plan(CPS, HOSTVARS, CPS[0], manifest(), "20261207T031500Z", bump_revision=0)
