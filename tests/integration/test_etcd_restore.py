"""The restore of a stacked etcd, rehearsed with etcd's own programs at the pinned version (etcd, etcdctl and etcdutl
v3.5.35, built by build-binaries.sh): three members on loopback addresses with TLS between peers, as kubeadm's are.

The commands are the ones etcd_restore.yml runs, from the plan the etcd_restore_plan filter makes for each member out
of a kubeadm-shaped manifest (less the `ctr run` that starts etcdutl from the etcd image on a site): etcdctl takes a
snapshot, a key is deleted and another written after it, every member stops, `etcdutl snapshot status` reads the
snapshot, `etcdutl snapshot restore` rebuilds each member's data directory, the old one is kept and the new one moved
into place, and the members start with their unchanged flags. The deleted key is back, the later one gone, the
members are the inventory's, and the revision moved on by the bump and the past is compacted: every watcher lists
afresh. Loopback only (127.0.0.31-33): the API lane.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import shutil
import subprocess
import time

import pytest
from helpers import ROOT, built_program

from ansible_collections.kuberos.platform.plugins.filter.etcd_restore_plan import etcd_restore_plan
from ansible_collections.kuberos.platform.plugins.filter.etcd_snapshot_status import etcd_snapshot_status
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

BUILD = os.path.join(ROOT, "roles", "local_cluster", "files", "build-binaries.sh")
HOSTS = {"edge-a.site": "127.0.0.31", "edge-b.site": "127.0.0.32", "edge-c.site": "127.0.0.33"}
HOSTVARS = {host: {"kuberos_node_name": host.split(".")[0], "kuberos_address": address} for host, address in HOSTS.items()}
STAMP = "20261207T040000Z"


@pytest.fixture(scope="module")
def programs():
    env = {**os.environ, "SKIP_KUBECTL": "1", "SKIP_KUBEADM": "1"}
    return {name: built_program(BUILD, name, env) for name in ("etcd", "etcdctl", "etcdutl")}


def _peer_certificate(folder: str) -> None:
    """A CA and one peer certificate for every member (server and client use, as kubeadm's etcd peer certificates),
    valid for the members' addresses and 127.0.0.1 (the source address of their connections)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    ca, ca_key = pki.new_ca("etcd-ca", days=1)
    key = pki.new_key()
    now = datetime.datetime.now(datetime.UTC)
    addresses = [*HOSTS.values(), "127.0.0.1"]
    certificate = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "etcd-peer")]))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address(a)) for a in addresses]), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    for name, item in (("ca.crt", ca), ("peer.crt", certificate), ("peer.key", key)):
        pki.write_pem(os.path.join(folder, name), item)


class Members:
    """Three etcd members as kubeadm runs them (its flags, less the client TLS), each with its own /var/lib under
    ``root``."""

    def __init__(self, programs: dict, root: str):
        self.programs, self.root, self.processes, self.logs = programs, root, [], []

    def data_dir(self, host: str) -> str:
        return os.path.join(self.root, host, "var", "lib", "etcd")

    def manifest(self, host: str) -> dict:
        """The member's etcd.yaml as kubeadm writes it, as far as the restore reads it."""
        name, address = HOSTVARS[host]["kuberos_node_name"], HOSTS[host]
        command = [
            "etcd",
            f"--name={name}",
            f"--data-dir={self.data_dir(host)}",
            f"--initial-advertise-peer-urls=https://{address}:2380",
        ]
        return {"spec": {"containers": [{"name": "etcd", "image": "registry.k8s.io/etcd:3.5.35-0", "command": command}],
                         "volumes": [{"name": "etcd-data", "hostPath": {"path": self.data_dir(host)}}]}}  # fmt: skip

    def start(self) -> None:
        cluster = ",".join(f"{v['kuberos_node_name']}=https://{HOSTS[h]}:2380" for h, v in HOSTVARS.items())
        pki_dir = self.root
        for host, address in HOSTS.items():
            argv = [
                self.programs["etcd"], f"--name={HOSTVARS[host]['kuberos_node_name']}", f"--data-dir={self.data_dir(host)}",
                f"--listen-client-urls=http://{address}:2379", f"--advertise-client-urls=http://{address}:2379",
                f"--listen-peer-urls=https://{address}:2380", f"--initial-advertise-peer-urls=https://{address}:2380",
                f"--initial-cluster={cluster}", "--initial-cluster-state=new", "--snapshot-count=10000",
                f"--peer-cert-file={pki_dir}/peer.crt", f"--peer-key-file={pki_dir}/peer.key",
                f"--peer-trusted-ca-file={pki_dir}/ca.crt", "--peer-client-cert-auth=true",
                f"--listen-metrics-urls=http://{address}:2381",
            ]  # fmt: skip
            self.logs.append(open(os.path.join(self.root, f"{host}.log"), "a", encoding="utf-8"))
            self.processes.append(subprocess.Popen(argv, stdout=self.logs[-1], stderr=self.logs[-1]))
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if self.ctl("endpoint", "health", "--cluster", check=False).returncode == 0:
                return
            time.sleep(0.5)
        raise AssertionError(
            f"the members did not become healthy within 60 s: {self.ctl('endpoint', 'health', '--cluster', check=False)}"
        )

    def stop(self) -> None:
        for process in self.processes:
            process.terminate()
        for process in self.processes:
            try:
                process.wait(20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(10)
        for log in self.logs:
            log.close()
        self.processes, self.logs = [], []

    def ctl(self, *argv: str, check: bool = True) -> subprocess.CompletedProcess:
        endpoint = f"http://{HOSTS['edge-a.site']}:2379"
        command = [self.programs["etcdctl"], f"--endpoints={endpoint}", "--dial-timeout=2s", "--command-timeout=10s", *argv]
        done = subprocess.run(command, capture_output=True, text=True, timeout=60, check=False)
        if check:
            assert done.returncode == 0, f"etcdctl {' '.join(argv)}: {done.stderr[-1500:]}"
        return done

    def revision(self) -> int:
        return json.loads(self.ctl("endpoint", "status", "-w", "json").stdout)[0]["Status"]["header"]["revision"]


def test_every_member_restored_from_one_snapshot_holds_its_state_with_the_revision_moved_on(programs, tmp_path):
    root = str(tmp_path)
    _peer_certificate(root)
    members = Members(programs, root)
    try:
        members.start()
        for index in range(40):
            members.ctl("put", f"/registry/configmaps/default/filler-{index}", "x" * 200)
        members.ctl("put", "/registry/configmaps/kuberos-system/deployment-record", "pick-and-place")
        snapshot = os.path.join(root, "etcd-snapshot.db")
        members.ctl("snapshot", "save", snapshot)
        members.ctl("del", "/registry/configmaps/kuberos-system/deployment-record")
        members.ctl("put", "/registry/configmaps/default/after-the-snapshot", "lost")
        revision_before = members.revision()
        members.stop()

        status_output = subprocess.run([programs["etcdutl"], "snapshot", "status", snapshot, "-w", "json"],
                                       capture_output=True, text=True, timeout=60, check=True).stdout  # fmt: skip
        status = etcd_snapshot_status(status_output)
        assert status["keys"] >= 41 and 41 <= status["revision"] < revision_before, status

        for host in HOSTS:
            plan = etcd_restore_plan(list(HOSTS), HOSTVARS, host, members.manifest(host), STAMP)
            shutil.copyfile(snapshot, plan["snapshot"])  # the playbook's copy
            argv = plan["restore_argv"]
            etcdutl = [programs["etcdutl"], *argv[argv.index("etcdutl") + 1 :]]  # on a site: ctr run <etcd image> etcdutl ...
            done = subprocess.run(etcdutl, capture_output=True, text=True, timeout=120, check=False)
            assert done.returncode == 0, done.stderr[-2000:]
            os.rename(plan["data_dir"], plan["kept_dir"])
            os.rename(plan["restored_dir"], plan["data_dir"])
            assert os.path.isdir(os.path.join(plan["kept_dir"], "member")), "the old data is kept"

        members.start()  # the same flags: etcd ignores --initial-* once its data directory exists
        record = members.ctl("get", "/registry/configmaps/kuberos-system/deployment-record", "--print-value-only")
        assert record.stdout.strip() == "pick-and-place"
        assert members.ctl("get", "/registry/configmaps/default/after-the-snapshot").stdout.strip() == ""
        listed = json.loads(members.ctl("member", "list", "-w", "json").stdout)["members"]
        assert sorted((m["name"], m["peerURLs"][0]) for m in listed) == [
            ("edge-a", "https://127.0.0.31:2380"), ("edge-b", "https://127.0.0.32:2380"), ("edge-c", "https://127.0.0.33:2380"),
        ]  # fmt: skip
        # past every revision a client saw before the restore, and the past compacted: watchers must list again
        assert members.revision() > 1_000_000_000 + status["revision"] - 1 > revision_before
        old = members.ctl(
            "get", "/registry/configmaps/kuberos-system/deployment-record", f"--rev={status['revision']}", check=False
        )
        assert old.returncode != 0 and "compacted" in old.stderr, old.stderr
        members.ctl("put", "/registry/configmaps/default/after-the-restore", "written")  # the restored cluster takes writes
    finally:
        members.stop()
