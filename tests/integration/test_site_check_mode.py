"""playbooks/site.yml --check --diff over a whole site of SSH hosts: nothing changes, every config is validated.

The site: two edge servers running the control plane (HA; edge-1 also the VPN gateway), a robot and a cloud
VM, each a network namespace with a real sshd and its own /etc (tests/sshlab.py). The play runs every role
of the cluster setup in check mode over SSH, as an infrastructure engineer would before the first real run:
node_prereqs, wireguard, kubeadm_init (the first control plane and a joining one), kubeadm_join (the robot and
the cloud VM), then stops before the pod network and the labels because no cluster exists yet. The real kubeadm (built
from the Go module proxy, the same program the kubeadm tests use) validates every host's rendered
configuration on the host. Checked: no failure, each host's configuration validated by kubeadm, nothing
written on any host (every file of every host's /etc hashed before and after), no secret on the output.
kubeadm init and join themselves cannot run here (no kubelet, no container runtime): see the kubeadm roles'
READMEs.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess

import pytest
import yaml
from helpers import ROOT, built_kubeadm, venv_tool
from sshlab import HostSpec, open_ssh_lab

pytestmark = pytest.mark.host  # its hosts are network namespaces with a real sshd

SITE = [
    HostSpec("edge-1", "edge"),
    HostSpec("edge-2", "edge"),
    HostSpec("fetch-1", "robot", ["video0"]),
    HostSpec("cloud-1", "cloud"),
]
MACHINE = {"kuberos_cpu": 4, "kuberos_memory": "8Gi"}


def site_inventory(lab, tmp_path_factory, kubeadm, **changes) -> str:
    """The lab site's inventory file; ``changes`` maps a host to variables to set (None: remove)."""
    address = {name: host.address for name, host in lab.hosts.items()}

    def host(name, **extra):
        values = {"ansible_host": address[name], "kuberos_address": address[name], **MACHINE, **extra}
        for key, value in changes.get(name, {}).items():
            values.pop(key, None) if value is None else values.__setitem__(key, value)
        return values

    inventory = {
        "all": {
            "vars": {
                **lab.connection_vars(),
                "kuberos_kubeconfig": str(tmp_path_factory.mktemp("admin") / "admin.conf"),
                "kubeadm_init_kubeadm_path": kubeadm,
                "kubeadm_join_kubeadm_path": kubeadm,
                # The lab hosts share this machine's kernel and have no route to package mirrors.
                "node_prereqs_load_modules": False,
                "node_prereqs_apt_update_cache": False,
                "node_prereqs_kubernetes_repo_url": "",
                "wireguard_hub_routed_networks": [f"{lab.subnet}.0/24"],
                **changes.get("all", {}),
            },
            "children": {
                "robots": {"hosts": {"fetch-1": host("fetch-1", kuberos_fleet="test-fleet", kuberos_devices=["camera"])}},
                "edge": {"hosts": {"edge-1": host("edge-1", kuberos_vpn_address="10.100.0.1"), "edge-2": host("edge-2")}},
                "cloud": {"hosts": {"cloud-1": host("cloud-1", kuberos_vpn_address="10.100.0.11", kuberos_gpu=1)}},
                "control_plane": {"hosts": {"edge-1": {}, "edge-2": {}}},
                "vpn_gateway": {"hosts": {"edge-1": {}}},
            },
        }
    }
    path = tmp_path_factory.mktemp("site") / "hosts.yml"
    path.write_text(yaml.safe_dump(inventory, sort_keys=False))
    return str(path)


@pytest.fixture(scope="module")
def site(request, tmp_path_factory):
    kubeadm = built_kubeadm()
    lab = open_ssh_lab(request, tmp_path_factory, SITE)
    return lab, site_inventory(lab, tmp_path_factory, kubeadm), kubeadm


def etc_digest(lab, name) -> dict[str, str]:
    """Every file of a host's private /etc (and /root/.ssh) by path -> sha256."""
    digests = {}
    home = lab.hosts[name].home
    for top in ("etc", "root-ssh"):
        for directory, _dirs, files in os.walk(os.path.join(home, top)):
            for file in files:
                full = os.path.join(directory, file)
                if os.path.islink(full) or not os.path.isfile(full):
                    continue
                with open(full, "rb") as handle:
                    digests[os.path.relpath(full, home)] = hashlib.sha256(handle.read()).hexdigest()
    return digests


def run_site(inventory: str, *extra: str) -> tuple[subprocess.CompletedProcess, dict]:
    env = {
        **os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_STDOUT_CALLBACK": "ansible.posix.json",
        "ANSIBLE_NOCOLOR": "1",
    }  # fmt: skip
    command = [venv_tool("ansible-playbook"), "playbooks/site.yml", "-i", inventory, *extra]
    done = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    try:
        report = json.loads(done.stdout)
    except json.JSONDecodeError:
        pytest.fail(f"site.yml printed no JSON report (exit {done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return done, report


def task_hosts(report: dict, role: str, name: str) -> dict[str, dict]:
    """host -> result of the task ``<role> : <name>`` (as the JSON callback names role tasks)."""
    found = {}
    for play in report["plays"]:
        for task in play["tasks"]:
            if task["task"]["name"] in (name, f"{role} : {name}", f"kuberos.platform.{role} : {name}"):
                found.update(task["hosts"])
    return found


def failures(report: dict) -> list[str]:
    """Each failed or unreachable task result: play, task, host and message."""
    found = []
    for play in report["plays"]:
        for task in play["tasks"]:
            for host, result in task["hosts"].items():
                if result.get("failed") or result.get("unreachable"):
                    where = f"{play['play']['name']} / {task['task']['name']} / {host}"
                    items = [r for r in result.get("results", []) if r.get("failed")]
                    for item in items or [result]:
                        message = item.get("msg") or item.get("stderr") or ""
                        message = f"{message}\n{item['problems']}" if item.get("problems") else str(message)[:700]
                        label = f" [{item.get('item')}]" if items else ""
                        found.append(f"{where}{label}: {message}")
    return found


def test_site_check_mode_changes_nothing_and_validates_every_config(site):
    lab, inventory, _kubeadm = site
    before = {name: etc_digest(lab, name) for name in lab.hosts}
    done, report = run_site(inventory, "--check", "--diff")
    stats = report["stats"]
    assert done.returncode == 0, "\n".join(failures(report)) or done.stderr[-3000:]
    for name in lab.hosts:
        assert stats[name]["failures"] == 0 and stats[name]["unreachable"] == 0, (name, stats[name])

    # kubeadm validated each control plane's and each worker's configuration on the host itself.
    init = task_hosts(report, "kubeadm_init", "Validate the configuration with kubeadm")
    join = task_hosts(report, "kubeadm_join", "Validate the configuration with kubeadm")
    for name, results in (("edge-1", init), ("edge-2", init), ("fetch-1", join), ("cloud-1", join)):
        result = results.get(name)
        assert result and not result.get("skipped") and result.get("rc") == 0, (name, result)

    # What the control planes would write: edge-1 initialises, edge-2 joins as a control plane (secrets not made).
    plans = task_hosts(report, "kubeadm_init", "Render this control plane's kubeadm configuration (join secrets as placeholders)")
    assert plans["edge-1"]["ansible_facts"]["kubeadm_init__plan"]["action"] == "init"
    assert plans["edge-2"]["ansible_facts"]["kubeadm_init__plan"]["action"] != "init"
    worker = task_hosts(report, "kubeadm_join", "Render this worker's kubeadm configuration (join secrets as placeholders)")
    cloud = worker["cloud-1"]["ansible_facts"]["kubeadm_join__plan"]["content"]
    assert "node-ip" in cloud and "10.100.0.11" in cloud, cloud  # the cloud VM registers with its tunnel address
    robot = worker["fetch-1"]["ansible_facts"]["kubeadm_join__plan"]["content"]
    assert "kuberos.io/robot" in robot and "NoSchedule" in robot, robot  # robots accept only placed modules

    # Nothing was written on any host, and the play stopped before the pod network (no cluster yet).
    after = {name: etc_digest(lab, name) for name in lab.hosts}
    for name in lab.hosts:
        changed = sorted(set(before[name].items()) ^ set(after[name].items()))
        assert not changed, f"check mode changed files on {name}: {changed[:10]}"
    assert not task_hosts(report, "calico", "Render Calico's objects")
    assert not task_hosts(report, "cilium", "Render Cilium's objects")


def test_a_bad_inventory_is_refused_before_any_machine_is_touched(site, tmp_path_factory):
    """A cloud VM without its tunnel address and a malformed pod network: a real run (no --check) stops in the
    first play, on this machine, naming each host and variable; no task ran on any machine."""
    lab, _inventory, kubeadm = site
    inventory = site_inventory(
        lab, tmp_path_factory, kubeadm, **{"cloud-1": {"kuberos_vpn_address": None}, "all": {"kuberos_pod_cidr": "10.244.0.0/33"}}
    )
    before = {name: etc_digest(lab, name) for name in lab.hosts}
    done, report = run_site(inventory)
    problems = "\n".join(failures(report))
    assert done.returncode != 0
    assert "cloud-1" in problems and "kuberos_vpn_address" in problems, problems
    assert "10.244.0.0/33" in problems, problems
    assert "Traceback" not in problems and "Traceback" not in done.stderr
    assert all(line.startswith("Check the inventory before any machine is touched") for line in failures(report)), problems
    assert len(failures(report)) == 1 and problems.count("hosts.cloud-1.kuberos_vpn_address") == 1, problems  # once
    assert set(report["stats"]) == {"localhost"}, report["stats"]  # no machine was contacted
    assert {name: etc_digest(lab, name) for name in lab.hosts} == before


def test_an_unknown_cni_is_refused_before_any_machine_is_touched(site, tmp_path_factory):
    """kuberos_cni names a pod network the collection does not install: the first play stops, naming the variable,
    the value and the choices; no machine was contacted."""
    lab, _inventory, kubeadm = site
    inventory = site_inventory(lab, tmp_path_factory, kubeadm, **{"all": {"kuberos_cni": "flannel"}})
    done, report = run_site(inventory)
    problems = "\n".join(failures(report))
    assert done.returncode != 0
    assert 'kuberos_cni: "flannel" is not a CNI this collection installs (calico or cilium)' in problems, problems
    assert set(report["stats"]) == {"localhost"}, report["stats"]
