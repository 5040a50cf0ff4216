"""The control_plane_vip role's own checks, run by ansible-playbook on this machine (a local connection, its files in
a temporary folder, in check mode): giving the virtual IP up (``control_plane_vip_state: absent``, as reset.yml does) works with a
control plane missing from the play, as on a site where one is dead; holding it (``present``) with one missing is
refused, naming the control plane without an address."""

from __future__ import annotations

import subprocess

import yaml
from helpers import ROOT, venv_tool


def _run(tmp_path, state: str) -> subprocess.CompletedProcess:
    config = tmp_path / "keepalived"
    config.mkdir(exist_ok=True)
    for name in ("keepalived.conf", "kuberos-apiserver-check", "kuberos-vrrp.secret"):
        (config / name).write_text("left by an earlier run\n")
    hosts = {name: {"kuberos_address": f"192.0.2.{11 + i}"} for i, name in enumerate(("edge-a", "edge-b", "edge-c"))}
    inventory = {"all": {"vars": {"kuberos_control_plane_vip": "192.0.2.10", "ansible_connection": "local",
                                  "ansible_python_interpreter": "{{ ansible_playbook_python }}"},
                         "children": {"control_plane": {"hosts": hosts}}}}  # fmt: skip
    (tmp_path / "hosts.yml").write_text(yaml.safe_dump(inventory))
    play = [{"hosts": "control_plane", "gather_facts": False, "roles": [{
        "role": "kuberos.platform.control_plane_vip",
        "vars": {"control_plane_vip_state": state, "control_plane_vip_config_dir": str(config)},
    }]}]  # fmt: skip
    (tmp_path / "play.yml").write_text(yaml.safe_dump(play))
    # check mode: a keepalived on this machine stays as it is
    command = [venv_tool("ansible-playbook"), str(tmp_path / "play.yml"), "-i", str(tmp_path / "hosts.yml"),
               "--limit", "edge-a,edge-c", "--check"]  # fmt: skip
    env = {"ANSIBLE_CONFIG": f"{ROOT}/ansible.cfg", "ANSIBLE_NOCOLOR": "1", "PATH": "/usr/bin:/bin:/usr/sbin:/sbin"}
    return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300, check=False)


def test_the_virtual_ip_is_given_up_with_a_control_plane_missing(tmp_path):
    done = _run(tmp_path, "absent")
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    removal = done.stdout.split("Remove its configuration and health check")[1].split("TASK [")[0]
    assert removal.count("changed: [edge-a]") == 3 and removal.count("changed: [edge-c]") == 3, removal


def test_holding_it_with_a_control_plane_missing_is_refused_naming_it(tmp_path):
    done = _run(tmp_path, "present")
    said = " ".join(done.stdout.split())
    assert done.returncode != 0 and "an empty one is a control plane that left this play" in said, done.stdout[-4000:]
    assert "the others: ['', '192.0.2.13']" in said or "the others: ['192.0.2.11', '']" in said, done.stdout[-4000:]
    assert (tmp_path / "keepalived" / "keepalived.conf").exists()
