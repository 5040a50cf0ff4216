"""playbooks/import_reference.yml end to end with ansible-playbook: the example reference site (ClusterInventory and
Fleet) becomes an inventory file that Ansible reads and the scheduler's inventory parser accepts; a second run changes
nothing, check mode writes nothing, diff shows the file, and bad input fails naming file, line and field."""

from __future__ import annotations

import json
import os
import re
import subprocess

import pytest
from helpers import ROOT, venv_tool

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.ansible_inventory import read_inventory

pytestmark = pytest.mark.playbook

EXAMPLE = "examples/reference/site"


def import_reference(dest, *extra, cluster_inventory=f"{EXAMPLE}/cluster_inventory.yml", fleets=f"{EXAMPLE}/fleet.yml"):
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1", "ANSIBLE_FORCE_COLOR": "0"}
    command = [
        venv_tool("ansible-playbook"),
        "playbooks/import_reference.yml",
        "-e",
        f"cluster_inventory={cluster_inventory}",
        "-e",
        f"fleets={fleets}",
        "-e",
        f"dest={dest}",
        *extra,
    ]
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    recap = re.search(r"localhost\s+: ok=(\d+)\s+changed=(\d+)\s+unreachable=\d+\s+failed=(\d+)", result.stdout)
    result.changed = int(recap.group(2)) if recap else None
    return result


def host_vars(inventory: str, host: str) -> dict:
    """A host's variables as Ansible reads them (every variable, not only the resource model's)."""
    done = subprocess.run(
        [venv_tool("ansible-inventory"), "-i", inventory, "--host", host], capture_output=True, text=True, timeout=120, check=True
    )
    return json.loads(done.stdout)


def test_example_site_is_imported_and_the_parser_accepts_it(tmp_path):
    dest = tmp_path / "hall-b" / "hosts.yml"
    first = import_reference(dest)
    assert first.returncode == 0, first.stdout + first.stderr
    assert first.changed == 1
    assert "kuberos_cpu and kuberos_memory are placeholders" in first.stdout  # the notes are printed
    text = dest.read_text()
    assert text.startswith("---\n# Imported from a reference KubeROS site")
    assert "kuberos_cpu: 2  # placeholder: write the machine's own" in text

    model = load_inventory(read_inventory(str(dest)), source=str(dest))
    assert model.fleets == {"mir-fleet": ("mir-1", "mir-2")}
    assert {name: node.tier for name, node in model.nodes.items()} == {
        "hall-b-edge-1": "edge",
        "hall-b-edge-2": "edge",
        "hall-b-master": "edge",
        "mir-1": "onboard",
        "mir-2": "onboard",
    }
    assert model.nodes["mir-1"].devices == frozenset({"ur-arm", "lidar"})
    assert not model.nodes["hall-b-edge-2"].shared and model.nodes["hall-b-edge-1"].shared

    mir1 = host_vars(str(dest), "mir-1")
    assert mir1["ansible_host"] == "10.20.1.11"
    assert mir1["kuberos_devices"] == ["ur-arm", "lidar"]
    assert mir1["kuberos_device_parameters"] == {
        "ur-arm": {"robot-ip": "10.20.1.111", "ur-type": "ur10e", "headless": True},
        "lidar": {"frame-id": "base_laser", "scan-frequency": 25},
    }
    listing = subprocess.run(
        [venv_tool("ansible-inventory"), "-i", str(dest), "--list"], capture_output=True, text=True, timeout=120, check=True
    )
    assert json.loads(listing.stdout)["control_plane"]["hosts"] == ["hall-b-master"]

    second = import_reference(dest)
    assert second.returncode == 0 and second.changed == 0, second.stdout
    assert dest.read_text() == text


def test_check_mode_writes_nothing_and_diff_shows_the_change(tmp_path):
    dest = tmp_path / "hosts.yml"
    checked = import_reference(dest, "--check", "--diff")
    assert checked.returncode == 0 and checked.changed == 1, checked.stdout + checked.stderr
    assert not dest.exists()
    assert re.search(r"^\+\s+kuberos_fleet: mir-fleet$", checked.stdout, re.M), checked.stdout

    assert import_reference(dest).returncode == 0
    changed = import_reference(dest, "--check", "--diff", "-e", '{"default_cpu": {"onboard": 6}}')
    assert changed.returncode == 0 and changed.changed == 1, changed.stdout
    assert re.search(r"^-\s+kuberos_cpu: 2  # placeholder", changed.stdout, re.M), changed.stdout
    assert re.search(r"^\+\s+kuberos_cpu: 6  # placeholder", changed.stdout, re.M), changed.stdout
    assert "kuberos_cpu: 2  #" in dest.read_text()


def test_a_file_it_did_not_write_is_kept_unless_forced(tmp_path):
    dest = tmp_path / "hosts.yml"
    dest.write_text("all:\n  hosts:\n    mine:\n")
    refused = import_reference(dest)
    assert refused.returncode != 0
    assert "exists and was not written by this module" in refused.stdout
    assert dest.read_text() == "all:\n  hosts:\n    mine:\n"
    forced = import_reference(dest, "-e", "force=true")
    assert forced.returncode == 0 and forced.changed == 1, forced.stdout
    assert "mir-1:" in dest.read_text()


def test_bad_input_fails_naming_file_line_and_field(tmp_path):
    source = os.path.join(ROOT, EXAMPLE, "cluster_inventory.yml")
    with open(source, encoding="utf-8") as handle:
        text = handle.read().replace("deviceName: lidar\n        parameter:", "deviceName: Lidar_2D\n        parameter:")
    bad = tmp_path / "cluster_inventory.yml"
    bad.write_text(text)
    fleet = tmp_path / "fleet.yml"
    with open(os.path.join(ROOT, EXAMPLE, "fleet.yml"), encoding="utf-8") as handle:
        fleet.write_text(handle.read() + "  - name: mir-3\n")
    dest = tmp_path / "hosts.yml"
    result = import_reference(dest, cluster_inventory=bad, fleets=fleet)
    assert result.returncode != 0
    line = text.splitlines().index("      - deviceName: Lidar_2D") + 1
    assert (
        f"{os.path.realpath(bad)}:{line}: hosts[1].peripheralDevices[1].deviceName: 'Lidar_2D' is not a valid device name"
        in result.stdout
    )
    assert f"{os.path.realpath(fleet)}:12: robot[2].name: 'mir-3' is not a robot of the ClusterInventory" in result.stdout
    assert "Traceback" not in result.stdout + result.stderr
    assert not dest.exists()
