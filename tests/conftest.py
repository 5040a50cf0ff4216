"""Shared fixtures: the repository root, the embedded inventory as the scheduler sees it."""

from __future__ import annotations

import functools
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
VENV_BIN = os.path.join(ROOT, ".venv", "bin")


@functools.cache
def inventory_raw(path: str = "inventories/local") -> dict:
    """Read an inventory with Ansible's own inventory manager, then the fleet_inventory filter."""
    from ansible.inventory.manager import InventoryManager
    from ansible.parsing.dataloader import DataLoader
    from ansible.vars.manager import VariableManager

    from ansible_collections.kuberos.platform.plugins.filter.fleet_inventory import fleet_inventory

    loader = DataLoader()
    manager = InventoryManager(loader=loader, sources=[os.path.join(ROOT, path)])
    variables = VariableManager(loader=loader, inventory=manager)
    groups = {name: [h.name for h in group.get_hosts()] for name, group in manager.groups.items()}
    hostvars = {}
    for host in manager.get_hosts():
        values = variables.get_vars(host=host, include_hostvars=False)
        hostvars[host.name] = {k: v for k, v in values.items() if k.startswith("kuberos_")}
    return fleet_inventory(groups, hostvars)


@pytest.fixture(scope="session")
def local_raw() -> dict:
    return inventory_raw()


@pytest.fixture(scope="session")
def local_inventory(local_raw):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory

    return load_inventory(local_raw)


@pytest.fixture(scope="session")
def root() -> str:
    return ROOT


def venv_tool(name: str) -> str:
    path = os.path.join(VENV_BIN, name)
    return path if os.path.exists(path) else os.path.join(os.path.dirname(sys.executable), name)
