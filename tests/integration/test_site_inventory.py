"""The inventory check that opens site.yml: the sample inventory, the documented starting point, passes it, and a bad
inventory's problems are each reported once, however many machines share them, with no machine contacted."""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest
import yaml
from helpers import ROOT, venv_tool

pytestmark = pytest.mark.playbook


def first_play(tmp_path, inventory: str) -> subprocess.CompletedProcess:
    """site.yml's first play alone (the same task), against ``inventory``."""
    with open(os.path.join(ROOT, "playbooks", "site.yml"), encoding="utf-8") as handle:
        site = yaml.safe_load(handle)
    playbook = tmp_path / "first-play.yml"
    playbook.write_text(yaml.safe_dump([site[0]], sort_keys=False))
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1"}
    return subprocess.run(
        [venv_tool("ansible-playbook"), str(playbook), "-i", inventory], cwd=ROOT, env=env, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip


def test_the_sample_inventory_passes_the_first_play(tmp_path):
    done = first_play(tmp_path, os.path.join(ROOT, "inventories", "sample"))
    assert done.returncode == 0, done.stdout + done.stderr
    assert "ok=2" in done.stdout and "failed=0" in done.stdout  # the machines and the VPN, then the CNI choice


def test_each_problem_is_reported_once(tmp_path):
    inventory = tmp_path / "sample"
    shutil.copytree(os.path.join(ROOT, "inventories", "sample"), inventory)
    hosts = (inventory / "hosts.yml").read_text()
    hosts = hosts.replace("kuberos_address: 192.168.40.11", "kuberos_address: edge-a.site.example.internal")
    hosts = hosts.replace("kuberos_vpn_address: 10.99.0.12", "kuberos_vpn_address: 10.99.0.11")
    (inventory / "hosts.yml").write_text(hosts)
    done = first_play(tmp_path, str(inventory))
    output = done.stdout + done.stderr
    assert done.returncode != 0
    assert "the inventory cannot make a site (2 problems; nothing was touched)" in output
    address = "hosts.edge-a.site.example.internal.kuberos_address: 'edge-a.site.example.internal' is not valid"
    assert output.count(address) == 1, output
    assert output.count("hosts.gpu-vm-2.kuberos_vpn_address: 10.99.0.11 is also gpu-vm-1's") == 1, output
    assert "fetch-01" not in output  # no machine's name in a loop label: one task, one report


def test_a_virtual_ip_that_is_taken_or_not_the_endpoint_is_refused(tmp_path):
    inventory = tmp_path / "sample"
    shutil.copytree(os.path.join(ROOT, "inventories", "sample"), inventory)
    site = (inventory / "group_vars" / "all.yml").read_text()
    site = site.replace("kuberos_control_plane_vip: 192.168.40.10", "kuberos_control_plane_vip: 192.168.40.12")
    site = site.replace("k8s-api.site.example.internal:6443", "192.168.40.10:6443")
    (inventory / "group_vars" / "all.yml").write_text(site)
    done = first_play(tmp_path, str(inventory))
    output = done.stdout + done.stderr
    assert done.returncode != 0
    assert "the inventory cannot make a site (2 problems; nothing was touched)" in output, output[-3000:]
    assert output.count("192.168.40.12 is also hosts.edge-b.site.example.internal.kuberos_address") == 1, output
    assert output.count("'192.168.40.10:6443' names 192.168.40.10, not the virtual IP 192.168.40.12") == 1, output


def test_a_virtual_ip_that_is_no_address_is_refused(tmp_path):
    inventory = tmp_path / "sample"
    shutil.copytree(os.path.join(ROOT, "inventories", "sample"), inventory)
    site = (inventory / "group_vars" / "all.yml").read_text()
    (inventory / "group_vars" / "all.yml").write_text(site.replace("vip: 192.168.40.10", "vip: k8s-vip"))
    done = first_play(tmp_path, str(inventory))
    assert done.returncode != 0
    assert "vars.kuberos_control_plane_vip: 'k8s-vip' is not an IP address" in done.stdout + done.stderr
