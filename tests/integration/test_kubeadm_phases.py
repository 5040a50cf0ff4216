"""The kubeadm configurations with the real kubeadm v1.34.4, built from the Go module proxy like the control plane.

Every configuration the roles would write (rendered by the kubeadm_config filter, the roles' own path, and written
as the roles write them) goes through `kubeadm config validate`; the first control plane's certificate and kubeconfig
phases run for real into a temporary directory and their results are read back with `cryptography`. The roles run in
check mode against this machine (connection local) with their paths in the temporary directory, and for real on hosts
that have already joined, where a second run must change nothing. A kubelet joining for real cannot run here (see the
roles' READMEs).
"""

from __future__ import annotations

import copy
import ipaddress
import json
import os
import subprocess
import sys

import pytest
import yaml
from cryptography import x509
from helpers import ROOT, built_kubeadm, venv_tool

from ansible_collections.kuberos.platform.plugins.filter.kubeadm_config import kubeadm_config
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.kubeadm_config import to_yaml

ENDPOINT = "k8s.site.example:6443"
HARDWARE = {"kuberos_cpu": 4, "kuberos_memory": "8Gi"}
HOSTS = {
    "edge-1": {**HARDWARE, "kuberos_address": "10.0.0.11"},
    "edge-2": {**HARDWARE, "kuberos_address": "10.0.0.12", "kuberos_vpn_address": "10.99.0.2"},
    "edge-3": {**HARDWARE, "kuberos_address": "10.0.0.13"},
    "edge-4": {**HARDWARE, "kuberos_address": "10.0.0.14", "kuberos_fleets": ["picking"]},
    "fetch-1": {**HARDWARE, "kuberos_address": "10.0.1.5", "kuberos_fleet": "picking", "kuberos_devices": ["camera"]},
    "cloud-1": {**HARDWARE, "ansible_host": "203.0.113.7", "kuberos_vpn_address": "10.99.0.11", "kuberos_gpu": 1},
}
GROUPS = {"robots": ["fetch-1"], "edge": ["edge-1", "edge-2", "edge-3", "edge-4"], "cloud": ["cloud-1"]}
RAW = {"hosts": {h: {k: v for k, v in hv.items() if k not in ("kuberos_address", "ansible_host", "kuberos_vpn_address")}
                 for h, hv in HOSTS.items()}, "groups": GROUPS}  # fmt: skip
SINGLE = {"control_planes": ["edge-1"], "options": {}}
HA = {"control_planes": ["edge-1", "edge-2", "edge-3"], "options": {"control_plane_endpoint": ENDPOINT}}
JOIN_COMMAND = f"kubeadm join {ENDPOINT} --token k8sabc.0123456789qwerty --discovery-token-ca-cert-hash sha256:{'ab' * 32}"
UPLOAD_CERTS = "[upload-certs] Using certificate key:\n" + "cd" * 32 + "\n"


@pytest.fixture(scope="module")
def kubeadm():
    return built_kubeadm()


def render(host, layout, **secrets):
    return kubeadm_config(RAW, HOSTS, host, layout["control_planes"], **layout["options"], **secrets)


def run(*argv, check=True):
    result = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=120)
    if check:
        assert result.returncode == 0, f"{' '.join(map(str, argv))}\n{result.stdout}\n{result.stderr}"
    return result


def write(path, content):
    path.write_text(content, encoding="utf-8")
    return path


VARIANTS = [
    ("single control plane", "edge-1", SINGLE, "init"),
    ("HA: the first control plane", "edge-1", HA, "init"),
    ("HA: the second control plane, with a VPN address", "edge-2", HA, "join-control-plane"),
    ("HA: the third control plane", "edge-3", HA, "join-control-plane"),
    ("edge worker", "edge-4", HA, "join-worker"),
    ("robot worker", "fetch-1", HA, "join-worker"),
    ("cloud worker", "cloud-1", SINGLE, "join-worker"),
]


@pytest.mark.parametrize(("variant", "host", "layout", "action"), VARIANTS, ids=[v[0] for v in VARIANTS])
@pytest.mark.parametrize("secrets", [False, True], ids=["placeholders", "secrets"])
def test_kubeadm_validates_every_rendered_configuration(kubeadm, tmp_path, variant, host, layout, action, secrets):
    given = {"join_command": JOIN_COMMAND, "certificate_key": UPLOAD_CERTS} if secrets else {}
    result = render(host, layout, **given)
    assert result["action"] == action
    path = write(tmp_path / f"kubeadm-{action.split('-')[0]}.yaml", result["content"])
    checked = run(kubeadm, "config", "validate", "--config", path)
    assert checked.stdout.strip() == "ok", checked.stderr
    registration = result["documents"][0]["nodeRegistration"]
    arguments = {a["name"]: a["value"] for a in registration["kubeletExtraArgs"]}
    if host == "fetch-1":
        assert registration["taints"] == [{"key": "kuberos.io/robot", "value": "fetch-1", "effect": "NoSchedule"}]
        assert "robot.kuberos.io/name=fetch-1" in arguments["node-labels"]
    if host == "cloud-1":
        assert arguments["node-ip"] == "10.99.0.11"
        assert result["documents"][0]["discovery"]["bootstrapToken"]["apiServerEndpoint"] == "10.0.0.11:6443"


def test_kubeadm_refuses_an_invalid_configuration(kubeadm, tmp_path):
    documents = copy.deepcopy(render("edge-1", SINGLE)["documents"])
    documents[1]["networking"]["podSubnet"] = "10.244.0.0/28"  # smaller than one node's /24
    path = write(tmp_path / "kubeadm-init.yaml", to_yaml(documents))
    refused = run(kubeadm, "config", "validate", "--config", path, check=False)
    assert refused.returncode != 0
    assert 'networking.podSubnet: Invalid value: "10.244.0.0/28"' in refused.stderr
    assert "smaller than the size of node subnet with mask 24" in refused.stderr


def _sans(cert):
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return set(names.get_values_for_type(x509.DNSName)), {str(ip) for ip in names.get_values_for_type(x509.IPAddress)}


@pytest.mark.parametrize(
    ("layout", "server", "names", "addresses"),
    [
        (SINGLE, "https://10.0.0.11:6443", set(), {"10.0.0.11"}),
        (HA, f"https://{ENDPOINT}", {"k8s.site.example"}, {"10.0.0.11", "10.0.0.12", "10.0.0.13", "10.99.0.2"}),
    ],
    ids=["single", "ha"],
)
def test_certificate_and_kubeconfig_phases_run_for_real(kubeadm, tmp_path, layout, server, names, addresses):
    documents = copy.deepcopy(render("edge-1", layout)["documents"])
    pki, kubeconfigs = tmp_path / "pki", tmp_path / "kubeconfigs"
    documents[1]["certificatesDir"] = str(pki)  # the one change: kubeadm's certificates go into the test directory
    path = write(tmp_path / "kubeadm-init.yaml", to_yaml(documents))
    run(kubeadm, "init", "phase", "certs", "all", "--config", path)
    run(kubeadm, "init", "phase", "kubeconfig", "all", "--config", path, "--kubeconfig-dir", kubeconfigs)

    ca = x509.load_pem_x509_certificate((pki / "ca.crt").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    apiserver = x509.load_pem_x509_certificate((pki / "apiserver.crt").read_bytes())
    apiserver.verify_directly_issued_by(ca)
    dns, ips = _sans(apiserver)
    assert names | {"edge-1", "kubernetes", "kubernetes.default.svc.cluster.local"} <= dns
    assert addresses | {"10.96.0.1"} <= ips  # the first address of the service network is the API's Service
    assert ipaddress.ip_address("10.0.0.11") in {ipaddress.ip_address(i) for i in ips}
    for name in ("etcd/ca.crt", "etcd/server.crt", "etcd/peer.crt", "front-proxy-ca.crt", "sa.pub"):
        assert (pki / name).exists(), name  # stacked etcd: its certificates live beside the API server's

    admin = yaml.safe_load((kubeconfigs / "admin.conf").read_text())
    assert admin["clusters"][0]["cluster"]["server"] == server
    kubelet = yaml.safe_load((kubeconfigs / "kubelet.conf").read_text())
    assert kubelet["users"][0]["name"] == "system:node:edge-1"
    assert (
        not os.path.exists("/etc/kubernetes/admin.conf")
        or os.path.getmtime("/etc/kubernetes/admin.conf") < ca.not_valid_before_utc.timestamp()
    )


# ----------------------------------------------------------------------------------------------- the roles


PLAYBOOK = """
- name: Control planes
  hosts: control_plane
  gather_facts: false
  roles:
    - role: kuberos.platform.kubeadm_init
- name: Workers
  hosts: robots:edge:cloud:!control_plane
  gather_facts: false
  roles:
    - role: kuberos.platform.kubeadm_join
"""


def _inventory(tmp_path, kubeadm, layout):
    hosts = {h: {**hv, "config_dir": str(tmp_path / "etc" / h)} for h, hv in HOSTS.items()}
    site = {
        "ansible_connection": "local",
        "ansible_python_interpreter": sys.executable,
        "kubeadm_init_kubeadm_path": kubeadm,
        "kubeadm_join_kubeadm_path": kubeadm,
        "kubeadm_init_config_dir": "{{ config_dir }}",
        "kubeadm_join_config_dir": "{{ config_dir }}",
        **({"kuberos_control_plane_endpoint": layout["options"]["control_plane_endpoint"]} if layout["options"] else {}),
    }
    children = {group: {"hosts": {h: hosts[h] for h in members}} for group, members in GROUPS.items()}
    children["control_plane"] = {"hosts": {h: {} for h in layout["control_planes"]}}
    inventory = write(tmp_path / "hosts.yml", yaml.safe_dump({"all": {"vars": site, "children": children}}))
    playbook = write(tmp_path / "kubeadm.yml", PLAYBOOK)
    return inventory, playbook


def play(inventory, playbook, *extra):
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_STDOUT_CALLBACK": "ansible.posix.json",
           "ANSIBLE_NOCOLOR": "1"}  # fmt: skip
    result = subprocess.run(
        [venv_tool("ansible-playbook"), "-i", str(inventory), str(playbook), *extra],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.stdout.lstrip().startswith("{"), result.stdout[-3000:] + result.stderr[-3000:]
    report = json.loads(result.stdout[result.stdout.index("{") :])
    tasks = {}
    for play_report in report["plays"]:
        for task in play_report["tasks"]:
            for host, outcome in task["hosts"].items():
                tasks.setdefault(task["task"]["name"].split(" : ", 1)[-1], {})[host] = outcome
    return result, report["stats"], tasks


def _files(folder):
    return sorted(os.path.relpath(os.path.join(d, f), folder) for d, _, files in os.walk(folder) for f in files)


@pytest.mark.playbook
@pytest.mark.parametrize("layout", [SINGLE, HA], ids=["single", "ha"])
def test_roles_in_check_mode_validate_and_change_nothing(kubeadm, tmp_path, layout):
    inventory, playbook = _inventory(tmp_path, kubeadm, layout)
    before = os.path.exists("/etc/kubernetes")
    result, stats, tasks = play(inventory, playbook, "--check", "--diff")
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert set(stats) == set(HOSTS)
    assert all(s["failures"] == 0 and s["unreachable"] == 0 for s in stats.values()), stats
    validated = {**tasks["Validate the configuration with kubeadm"]}
    assert set(validated) == set(HOSTS)  # every host's configuration went through the real kubeadm
    assert all(not outcome.get("skipped") and outcome["rc"] == 0 for outcome in validated.values()), validated
    for name in (
        "Create a bootstrap token for the joining workers",
        "Upload the control-plane certificates for the joining control planes",
    ):
        assert all(outcome.get("skipped") for outcome in tasks.get(name, {}).values()), name  # nothing ran on the cluster
    secret_writes = {
        **tasks["Write this worker's join configuration (bootstrap token; 0600, never shown)"],
        **tasks.get("Write this control plane's join configuration (bootstrap token and certificate key; 0600, never shown)", {}),
    }
    assert secret_writes and all(outcome.get("censored") for outcome in secret_writes.values())
    assert not (tmp_path / "etc").exists() or _files(tmp_path / "etc") == []  # nothing written
    assert os.path.exists("/etc/kubernetes") == before


@pytest.mark.playbook
def test_roles_leave_joined_hosts_alone_and_a_second_run_changes_nothing(kubeadm, tmp_path):
    inventory, playbook = _inventory(tmp_path, kubeadm, HA)
    for host in HOSTS:  # every host has joined already; the first control plane has its admin.conf
        folder = tmp_path / "etc" / host
        folder.mkdir(parents=True)
        (folder / "kubelet.conf").write_text("joined\n")
    (tmp_path / "etc" / "edge-1" / "admin.conf").write_text("initialised\n")

    first, stats, tasks = play(inventory, playbook)
    assert first.returncode == 0, first.stdout[-4000:] + first.stderr[-2000:]
    # The cluster exists (the control planes hold it), so nobody inits, nor joins: nothing changes, on the first
    # control plane neither (no API server answers here, and none is needed: nobody joins).
    assert all(s["changed"] == 0 for s in stats.values()), stats
    assert all(outcome.get("skipped") for outcome in tasks["Run kubeadm init"].values()), tasks["Run kubeadm init"]

    second, stats, tasks = play(inventory, playbook)
    assert second.returncode == 0, second.stdout[-4000:]
    assert all(s["changed"] == 0 and s["failures"] == 0 for s in stats.values()), stats
    assert sorted(_files(tmp_path / "etc")) == sorted([f"{h}/kubelet.conf" for h in HOSTS] + ["edge-1/admin.conf"])


# A stand-in for the cluster side of kubeadm: `config validate` is the real kubeadm; `token create` and `init phase
# upload-certs` print what the real ones print; `init` and `join` keep the configuration they were given and leave the
# admin.conf/kubelet.conf the real ones would. It shows how the roles move the secrets, not that a kubelet joins.
STAND_IN = """#!/bin/sh
set -e
case "$1 $2" in
  "config validate") exec {real} "$@" ;;
  "token create") echo "kubeadm join {endpoint} --token {token} --discovery-token-ca-cert-hash {ca_hash} " ;;
  "token delete") echo "$3" >> "{seen}/../deleted-tokens"; echo "bootstrap token \"$3\" deleted" ;;
  "init phase") printf '[upload-certs] Storing the certificates\\n[upload-certs] Using certificate key:\\n{key}\\n' ;;
  "init --config"|"join --config")
    dir=$(dirname "$3"); cp "$3" "{seen}/$(basename "$dir")-$1.yaml"
    [ "$1" = init ] && echo admin > "$dir/admin.conf"
    echo kubelet > "$dir/kubelet.conf" ;;
  *) echo "unexpected: $*" >&2; exit 2 ;;
esac
"""
TOKEN, CA_HASH, KEY = "k8sabc.0123456789qwerty", "sha256:" + "ab" * 32, "cd" * 32


@pytest.mark.playbook
def test_roles_join_with_secrets_that_never_show(kubeadm, tmp_path):
    seen = tmp_path / "seen"
    seen.mkdir()
    stand_in = write(
        tmp_path / "kubeadm",
        STAND_IN.format(real=kubeadm, endpoint=ENDPOINT, token=TOKEN, ca_hash=CA_HASH, key=KEY, seen=seen),
    )
    stand_in.chmod(0o755)
    inventory, playbook = _inventory(tmp_path, str(stand_in), HA)

    first, stats, tasks = play(inventory, playbook, "--diff")
    assert first.returncode == 0, first.stdout[-4000:] + first.stderr[-2000:]
    assert TOKEN not in first.stdout + first.stderr and KEY not in first.stdout + first.stderr
    assert "k8sabc" not in first.stdout  # not even the token's public id
    assert sorted(p.name for p in seen.iterdir()) == sorted(
        ["edge-1-init.yaml"] + [f"{h}-join.yaml" for h in HOSTS if h != "edge-1"]
    )
    for host in HOSTS:
        if host == "edge-1":
            continue
        join = yaml.safe_load((seen / f"{host}-join.yaml").read_text())
        assert join["discovery"]["bootstrapToken"]["token"] == TOKEN
        assert join["discovery"]["bootstrapToken"]["caCertHashes"] == [CA_HASH]
        assert ("controlPlane" in join) == (host in HA["control_planes"])
        if host in HA["control_planes"]:
            assert join["controlPlane"]["certificateKey"] == KEY
        assert not (tmp_path / "etc" / host / "kubeadm-join.yaml").exists()  # spent secrets are removed
    # One token and one certificate upload for the whole run, on the first control plane.
    assert len(tasks["Create a bootstrap token for the joining workers"]) == 1
    assert len(tasks["Upload the control-plane certificates for the joining control planes"]) == 1
    assert all(o.get("censored") for o in tasks["Create a bootstrap token for the joining workers"].values())
    # Each spent token deleted once the joins are done (the control planes', then the workers'), by its id only.
    assert (tmp_path / "deleted-tokens").read_text().split() == ["k8sabc", "k8sabc"]
    deletes = [*tasks["Delete the control planes' bootstrap token (spent)"].values(),
               *tasks["Delete the workers' bootstrap token (spent)"].values()]  # fmt: skip
    assert len(deletes) == 2 and all(o.get("censored") for o in deletes), deletes

    second, stats, _tasks = play(inventory, playbook, "--diff")
    assert second.returncode == 0, second.stdout[-4000:]
    assert all(s["changed"] == 0 and s["failures"] == 0 for s in stats.values()), stats
    assert len(list(seen.iterdir())) == len(HOSTS)  # nobody joined twice
    assert len((tmp_path / "deleted-tokens").read_text().split()) == 2  # and no token was made or deleted again
