"""playbooks/register_robot.yml against a real sshd: a lab robot (tests/sshlab.py) with a camera and a serial port.

Registration writes the robot's real hardware to the inventory, makes it a robot the scheduler accepts, installs
the cluster's key once, and is idempotent; check mode writes nothing. A wrong administrator's key, a changed host
key, an unreachable address and an unexpected fingerprint each fail with one clear sentence and write nothing.
"""

from __future__ import annotations

import base64
import hashlib
import os
import subprocess
import time

import pytest
import yaml
from helpers import ROOT, inventory_raw, playbook, venv_tool
from sshlab import HostSpec, open_ssh_lab

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory

pytestmark = [pytest.mark.playbook, pytest.mark.host]

ROBOT = "fetch-9"
FLEET = "test-fleet"
ARCH = {"x86_64": "amd64", "aarch64": "arm64"}


@pytest.fixture(scope="module")
def lab(request, tmp_path_factory):
    return open_ssh_lab(request, tmp_path_factory, [HostSpec(ROBOT, "robot", ["video0", "ttyUSB0"])])


def keypair(directory, name) -> str:
    path = os.path.join(directory, name)
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", name, "-f", path], check=True)
    return path


@pytest.fixture(autouse=True)
def json_results(monkeypatch):
    """Results as JSON, so that a failure's message is on one line, as written."""
    monkeypatch.setenv("ANSIBLE_CALLBACK_RESULT_FORMAT", "json")


@pytest.fixture(scope="module")
def cluster_key(tmp_path_factory) -> str:
    return keypair(tmp_path_factory.mktemp("cluster-key"), "cluster_ed25519") + ".pub"


def new_inventory(tmp_path, name="inventory") -> str:
    """An inventory directory with the user's own hosts.yml (an edge server), which registration never touches."""
    directory = tmp_path / name
    directory.mkdir()
    (directory / "hosts.yml").write_text("all:\n  children:\n    edge:\n      hosts:\n        edge-1:\n")
    (directory / "group_vars").mkdir()
    (directory / "group_vars" / "all.yml").write_text("kuberos_cpu: 8\nkuberos_memory: 16Gi\n")
    return str(directory)


def register(lab, inventory, cluster_key, *extra, address=None, admin_key=None):
    address = address or lab.hosts[ROBOT].address
    return playbook(
        "register_robot.yml", "-e", f"robot_register_name={ROBOT}", "-e", f"robot_register_address={address}",
        "-e", f"robot_register_fleet={FLEET}", "-e", f"robot_register_admin_key={admin_key or lab.admin_key}",
        "-e", f"robot_register_cluster_key={cluster_key}", "-e", "robot_register_join=false", *extra,
        inventory=inventory, timeout=300,
    )  # fmt: skip


def reach(inventory, private_key):
    """Run a command on the robot through the inventory, as the cluster's Ansible would: its key, the pinned host key."""
    ssh_args = f"-o UserKnownHostsFile={inventory}/.known_hosts -o StrictHostKeyChecking=yes -o IdentitiesOnly=yes"
    command = [
        venv_tool("ansible"), ROBOT, "-i", inventory, "-m", "ansible.builtin.command", "-a", "cat /etc/hostname",
        "-e", f"ansible_ssh_private_key_file={private_key}", "-e", "ansible_python_interpreter=/usr/bin/python3",
        "-e", f"ansible_ssh_common_args='{ssh_args}'",
    ]  # fmt: skip
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg")}
    return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)


def fingerprint(public_key: str) -> str:
    blob = base64.b64decode(public_key.split()[1])
    return "SHA256:" + base64.b64encode(hashlib.sha256(blob).digest()).decode().rstrip("=")


def files(inventory) -> dict[str, bytes]:
    found = {}
    for folder, _dirs, names in os.walk(inventory):
        for name in names:
            path = os.path.join(folder, name)
            with open(path, "rb") as handle:
                found[os.path.relpath(path, inventory)] = handle.read()
    return found


def output(result) -> str:
    """stdout and stderr with the callback's line wrapping undone."""
    return " ".join((result.stdout + result.stderr).split())


def authorized_keys(lab) -> str:
    with open(lab.path(ROBOT, "/root/.ssh/authorized_keys"), encoding="utf-8") as handle:
        return handle.read()


def failed_cleanly(result, before: dict, inventory) -> str:
    text = output(result)
    assert result.returncode != 0, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert files(inventory) == before, "a failed registration wrote to the inventory"
    return text


def test_registration_writes_the_robots_real_hardware(lab, cluster_key, tmp_path):
    inventory = new_inventory(tmp_path)
    first = register(lab, inventory, cluster_key)
    assert first.returncode == 0, first.stdout[-4000:] + first.stderr[-2000:]
    assert first.changed == 1

    with open(os.path.join(inventory, "host_vars", f"{ROBOT}.yml"), encoding="utf-8") as handle:
        written = yaml.safe_load(handle)
    meminfo = lab.exec(ROBOT, "cat", "/proc/meminfo").stdout
    mem_kib = int(next(line for line in meminfo.splitlines() if line.startswith("MemTotal:")).split()[1])
    address = lab.hosts[ROBOT].address
    assert written == {
        "kuberos_fleet": FLEET,
        "kuberos_cpu": int(lab.exec(ROBOT, "nproc").stdout),
        "kuberos_memory": written["kuberos_memory"],
        "kuberos_gpu": 0,
        "kuberos_arch": ARCH[lab.exec(ROBOT, "uname", "-m").stdout.strip()],
        "kuberos_devices": ["camera", "serial"],  # /dev/video0 and /dev/ttyUSB0 of the lab robot
        "kuberos_address": address,
        "ansible_host": address,
        "ansible_user": "root",
    }
    assert quantities.parse_memory(written["kuberos_memory"]) == mem_kib // 1024 * 1024**2  # whole MiB, rounded down

    # The user's hosts.yml is untouched; the robot is a member of robots through registered_robots.yml.
    assert open(os.path.join(inventory, "hosts.yml"), encoding="utf-8").read().count("fetch-9") == 0
    raw = inventory_raw.__wrapped__(inventory)
    assert ROBOT in raw["groups"]["robots"]
    node = load_inventory(raw).nodes[ROBOT]
    assert (node.tier, node.fleet, node.devices) == ("onboard", FLEET, frozenset({"camera", "serial"}))

    # The host key is pinned (trust on first use) and reported with its fingerprint.
    with open(os.path.join(inventory, ".known_hosts"), encoding="utf-8") as handle:
        assert handle.read() == f"{address} {lab.hosts[ROBOT].host_key}\n"
    assert fingerprint(lab.hosts[ROBOT].host_key) in output(first)

    with open(cluster_key, encoding="utf-8") as handle:
        key = " ".join(handle.read().split()[:2])
    assert authorized_keys(lab).count(key) == 1
    assert os.stat(lab.path(ROBOT, "/root/.ssh/authorized_keys")).st_mode & 0o777 == 0o600
    # The inventory entry is a usable host: Ansible reaches it with the cluster's key and the pinned host key.
    reached = reach(inventory, cluster_key.removesuffix(".pub"))
    assert reached.returncode == 0 and reached.stdout.split()[-1] == ROBOT, reached.stdout + reached.stderr

    before = files(inventory)
    second = register(lab, inventory, cluster_key)
    assert second.returncode == 0, second.stdout[-4000:]
    assert second.changed == 0
    assert files(inventory) == before
    assert authorized_keys(lab).count(key) == 1


def test_check_mode_contacts_the_robot_and_writes_nothing(lab, tmp_path):
    inventory = new_inventory(tmp_path)
    other_cluster_key = keypair(str(tmp_path), "other_cluster") + ".pub"
    before, keys_before = files(inventory), authorized_keys(lab)
    result = register(lab, inventory, other_cluster_key, "--check", "--diff")
    assert result.returncode == 0, result.stdout[-4000:]
    assert result.changed == 1
    assert files(inventory) == before
    assert authorized_keys(lab) == keys_before
    text = output(result)
    assert f"host_vars/{ROBOT}.yml" in text and "+kuberos_devices:" in text and "+- camera" in text


def test_a_wrong_admin_key_is_refused_and_nothing_is_written(lab, cluster_key, tmp_path):
    inventory = new_inventory(tmp_path)
    wrong = keypair(str(tmp_path), "not_the_admin")
    before = files(inventory)
    result = register(lab, inventory, cluster_key, admin_key=wrong)
    text = failed_cleanly(result, before, inventory)
    address = lab.hosts[ROBOT].address
    assert f"robot {ROBOT} refused the administrator's key {wrong} for root@{address} (authentication failed)" in text


def test_an_unreachable_robot_fails_fast(lab, cluster_key, tmp_path):
    inventory = new_inventory(tmp_path)
    before = files(inventory)
    started = time.monotonic()
    result = register(lab, inventory, cluster_key, "-e", "robot_register_connect_timeout=3", address=f"{lab.subnet}.250")
    elapsed = time.monotonic() - started
    text = failed_cleanly(result, before, inventory)
    assert f"cannot reach robot {ROBOT} at {lab.subnet}.250:" in text
    assert "check that it is powered on" in text
    assert elapsed < 3 + 30, f"took {elapsed:.0f} s"  # the connect timeout plus ansible-playbook's own start


def test_an_unexpected_fingerprint_is_refused_on_first_contact(lab, cluster_key, tmp_path):
    inventory = new_inventory(tmp_path)
    before = files(inventory)
    other = keypair(str(tmp_path), "impostor")
    with open(other + ".pub", encoding="utf-8") as handle:
        wrong = fingerprint(handle.read())
    result = register(lab, inventory, cluster_key, "-e", f"robot_register_expected_fingerprint={wrong}")
    text = failed_cleanly(result, before, inventory)
    presented = fingerprint(lab.hosts[ROBOT].host_key)
    assert f"presents the host key {presented}, not the expected {wrong}; refused, nothing was written" in text

    right = register(lab, inventory, cluster_key, "-e", f"robot_register_expected_fingerprint={presented}")
    assert right.returncode == 0, right.stdout[-4000:]
    assert os.path.exists(os.path.join(inventory, "host_vars", f"{ROBOT}.yml"))


# Last: it gives the lab robot a new host key.
def test_a_changed_host_key_is_refused_and_nothing_is_written(lab, cluster_key, tmp_path):
    inventory = new_inventory(tmp_path)
    registered = register(lab, inventory, cluster_key)
    assert registered.returncode == 0, registered.stdout[-4000:]
    pinned = fingerprint(lab.hosts[ROBOT].host_key)
    presented = fingerprint(lab.replace_host_key(ROBOT))
    # The robot's hardware changed too: still nothing may be written.
    with open(os.path.join(inventory, "host_vars", f"{ROBOT}.yml"), encoding="utf-8") as handle:
        text = handle.read()
    with open(os.path.join(inventory, "host_vars", f"{ROBOT}.yml"), "w", encoding="utf-8") as handle:
        handle.write(text.replace("kuberos_cpu:", "kuberos_cpu_before:"))
    before = files(inventory)
    result = register(lab, inventory, cluster_key)
    text = failed_cleanly(result, before, inventory)
    address = lab.hosts[ROBOT].address
    assert f"the host key of robot {ROBOT} at {address} has changed: pinned {pinned}" in text
    assert f"presented {presented}" in text
    assert f"ssh-keygen -R {address} -f {os.path.join(inventory, '.known_hosts')}" in text
