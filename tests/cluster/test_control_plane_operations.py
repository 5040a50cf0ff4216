"""etcd_restore.yml and certificates.yml run for real on three stand-in control planes on this machine
(tests/standin_control_planes.py: kubeadm v1.34.4's PKI per host, real etcd v3.5.35 members started and stopped by a
stand-in kubelet as their manifests come and go, stand-in API servers serving kubeadm's certificates); the restore's
last play lists the nodes of the local control plane through its kubeconfig, as it lists a site's through its
endpoint.

What stands in for a site: `ctr run <etcd image> etcdutl ...` runs the cache's etcdutl; `pgrep` answers "gone"; the
API servers, controller managers and schedulers only answer their health checks. The site chain runs the same
playbooks on lab machines (kuberos_lab/site_operations.py). etcd_backup.yml needs an etcd pod to exec into: it runs
there only.
"""

from __future__ import annotations

import base64
import json
import os
import re
import stat
import time

import pytest
import yaml
from cryptography import x509
from helpers import ROOT, built_kubeadm, built_program
from standin_control_planes import HOSTS, StandinSite

pytestmark = pytest.mark.cluster

BUILD = os.path.join(ROOT, "roles", "local_cluster", "files", "build-binaries.sh")
RECORD = "/registry/configmaps/kuberos-picking/kuberos-record-pick-and-place"
LATER = "/registry/configmaps/default/written-after-the-snapshot"


@pytest.fixture
def site(tmp_path):
    env = {**os.environ, "SKIP_KUBECTL": "1", "SKIP_KUBEADM": "1"}
    programs = {name: built_program(BUILD, name, env) for name in ("etcd", "etcdctl", "etcdutl")}
    programs["kubeadm"] = built_kubeadm()
    standin = StandinSite(tmp_path / "site", programs).setup()
    try:
        yield standin.start()
    finally:
        standin.stop()


def _snapshot(site, folder) -> str:
    """A record, a snapshot as etcd_backup.yml names it, then the record deleted and another key written."""
    for index in range(20):
        site.ctl("put", f"/registry/configmaps/default/filler-{index}", "x" * 100)
    site.ctl("put", RECORD, "pick-and-place")
    path = os.path.join(str(folder), "etcd-snapshot-20261207T040000Z-edge-a.db")
    site.ctl("snapshot", "save", path)
    site.ctl("del", RECORD)
    site.ctl("put", LATER, "lost by the restore")
    return path


def _revision(site) -> int:
    return json.loads(site.ctl("endpoint", "status", "-w", "json").stdout)[0]["Status"]["header"]["revision"]


def _tail(result) -> str:
    return result.stdout[-6000:] + result.stderr[-2000:]


def _said(result) -> str:
    """What the run printed, its whitespace collapsed (the callback folds long messages over lines)."""
    return " ".join((result.stdout + result.stderr).split())


def test_etcd_restore_rebuilds_every_member_from_one_snapshot(site, cluster, tmp_path):
    snapshot = _snapshot(site, tmp_path)
    name = os.path.basename(snapshot)
    refused = site.playbook("etcd_restore.yml", "-e", f"etcd_restore_snapshot={snapshot}")
    assert refused.returncode != 0 and "Refusing to restore" in _said(refused), _tail(refused)
    before = _revision(site)

    confirmed = ("-e", f"etcd_restore_snapshot={snapshot}", "-e", f"etcd_restore_confirm={name}",
                 "-e", f"kuberos_kubeconfig={cluster.kubeconfig}")  # fmt: skip
    checked = site.playbook("etcd_restore.yml", "--check", *confirmed)
    assert checked.returncode == 0, _tail(checked)
    assert "Check mode: would restore member edge-b (https://127.0.0.32:2380)" in _said(checked), _tail(checked)
    assert site.ctl("get", LATER, "--print-value-only").stdout.strip() == "lost by the restore"  # check mode changed nothing

    restored = site.playbook("etcd_restore.yml", *confirmed, "-e", "etcd_restore_wait_timeout=120")
    assert restored.returncode == 0, _tail(restored)
    assert "Restored 3 etcd members from " + name in _said(restored)
    assert site.ctl("get", RECORD, "--print-value-only").stdout.strip() == "pick-and-place"
    assert site.ctl("get", LATER).stdout.strip() == ""
    assert _revision(site) > 1_000_000_000 > before
    members = json.loads(site.ctl("member", "list", "-w", "json").stdout)["members"]
    assert sorted((m["name"], m["peerURLs"][0]) for m in members) == sorted((h, f"https://{a}:2380") for h, a in HOSTS.items())
    for host in HOSTS:
        lib = os.path.dirname(site.data_dir(host))
        assert sorted(os.listdir(lib)) == ["etcd", f"etcd.before-restore-{_stamp(restored)}"], os.listdir(lib)  # no copy left
        assert sorted(os.listdir(site.config_dir(host))) == ["admin.conf", "controller-manager.conf", "kubelet.conf", "manifests",
                                                             "pki", "scheduler.conf", "super-admin.conf"]  # fmt: skip
        assert len(os.listdir(os.path.join(site.config_dir(host), "manifests"))) == 4
    # every member stopped before any started again (all together, none left behind)
    stops = [i for i, (what, _h) in enumerate(site.events) if what == "stop etcd"]
    starts = [i for i, (what, _h) in enumerate(site.events) if what == "start etcd"][len(HOSTS) :]
    assert len(stops) == len(starts) == len(HOSTS) and max(stops) < min(starts), site.events


def _stamp(result) -> str:
    """The restore's UTC time, from the old data directory it names."""
    marker, said = "etcd.before-restore-", _said(result)
    start = said.index(marker) + len(marker)
    return said[start : start + len("20261207T040000Z")]


def test_a_member_that_fails_to_restore_puts_every_control_plane_back(site, cluster, tmp_path):
    snapshot = _snapshot(site, tmp_path)
    confirmed = ("-e", f"etcd_restore_snapshot={snapshot}", "-e", f"etcd_restore_confirm={os.path.basename(snapshot)}")
    result = site.playbook("etcd_restore.yml", *confirmed, "-e", f"kuberos_kubeconfig={cluster.kubeconfig}",
                           env={"FAIL_RESTORE_ON": "edge-b"})  # fmt: skip
    assert result.returncode != 0, _tail(result)
    said = _said(result)
    assert "was undone on every control plane" in said and "edge-b.site.example: Restore the snapshot" in said, _tail(result)
    assert "edge-a.site.example: Restore" not in said  # only the one that failed is named
    for host in HOSTS:
        assert os.listdir(os.path.dirname(site.data_dir(host))) == ["etcd"], host  # old data, nothing written beside it
        assert len(os.listdir(os.path.join(site.config_dir(host), "manifests"))) == 4, host
        assert not os.path.exists(os.path.join(site.config_dir(host), "etcd-restore-held-manifests")), host
    site.wait_healthy()  # the members are back on their old data: the key written after the snapshot is still there
    assert site.ctl("get", LATER, "--print-value-only").stdout.strip() == "lost by the restore"


def _not_after(path: str):
    with open(path, "rb") as handle:
        return x509.load_pem_x509_certificate(handle.read()).not_valid_after_utc


def _served_not_after(address: str, ca_file: str):
    import socket
    import ssl

    context = ssl.create_default_context(cafile=ca_file)
    with socket.create_connection((address, 6443), timeout=5) as raw, context.wrap_socket(raw, server_hostname=address) as tls:
        return x509.load_der_x509_certificate(tls.getpeercert(binary_form=True)).not_valid_after_utc


def test_certificates_are_reported_and_renewed_one_control_plane_at_a_time(site, tmp_path):
    kubeconfig = str(tmp_path / "controller" / "admin.conf")  # not the local cluster's: this playbook writes it
    report = site.playbook("certificates.yml", "-e", f"kuberos_kubeconfig={kubeconfig}")
    assert report.returncode == 0, _tail(report)
    assert "CERTIFICATE EXPIRES RESIDUAL DAYS" in _said(report)
    assert len(re.findall(r"\bapiserver \d{4}-\d\d-\d\dT", _said(report))) == len(HOSTS), _tail(report)
    checked = site.playbook("certificates.yml", "--check", "-e", "renew=true", "-e", f"kuberos_kubeconfig={kubeconfig}")
    assert checked.returncode == 0 and "Check mode: would renew every certificate of edge-a.site.example" in _said(checked)
    with open(os.path.join(site.folder, "kubeadm.log"), encoding="utf-8") as handle:
        assert " certs renew " not in handle.read()
    assert not os.path.exists(kubeconfig)

    crt = {h: os.path.join(site.config_dir(h), "pki", "apiserver.crt") for h in HOSTS}
    before = {h: _not_after(crt[h]) for h in HOSTS}
    time.sleep(1.1)  # notAfter has a resolution of a second
    site.events.clear()
    renewed = site.playbook("certificates.yml", "-e", "renew=true", "-e", f"kuberos_kubeconfig={kubeconfig}",
                            "-e", "certificates_wait_timeout=120")  # fmt: skip
    assert renewed.returncode == 0, _tail(renewed)
    assert _said(renewed).count("BEFORE RENEWAL MOVED") == len(HOSTS), _tail(renewed)
    for host, address in HOSTS.items():
        assert _not_after(crt[host]) > before[host], host
        # its API server restarted with the renewed certificate
        assert _served_not_after(address, os.path.join(site.config_dir(host), "pki", "ca.crt")) == _not_after(crt[host]), host
    # one control plane at a time: each host's static pods stopped and started before the next host's stopped
    order = [(what, host) for what, host in site.events if what.endswith("etcd")]
    assert order == [(what, host) for host in HOSTS for what in ("stop etcd", "start etcd")], site.events
    # the renewed admin.conf here, 0600 in a 0700 folder, with the first control plane's renewed client certificate
    assert (
        stat.S_IMODE(os.stat(kubeconfig).st_mode) == 0o600 and stat.S_IMODE(os.stat(os.path.dirname(kubeconfig)).st_mode) == 0o700
    )
    with open(kubeconfig, encoding="utf-8") as handle:
        user = yaml.safe_load(handle)["users"][0]["user"]
    copied = x509.load_pem_x509_certificate(base64.b64decode(user["client-certificate-data"])).not_valid_after_utc
    assert copied == _not_after_of_kubeconfig(os.path.join(site.config_dir("edge-a"), "admin.conf")) > before["edge-a"]
    assert "client-key-data" not in renewed.stdout and "BEGIN" not in renewed.stdout


def _not_after_of_kubeconfig(path: str):
    with open(path, encoding="utf-8") as handle:
        user = yaml.safe_load(handle)["users"][0]["user"]
    return x509.load_pem_x509_certificate(base64.b64decode(user["client-certificate-data"])).not_valid_after_utc
