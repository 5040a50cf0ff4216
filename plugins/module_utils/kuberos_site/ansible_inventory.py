"""An Ansible inventory (file or directory) read from outside a play, as the resource model's plain data.

An I/O helper for programs run from the checkout (the simulator, the benchmarks, the tests): it asks Ansible's own
command line (``ansible-inventory --list``, beside the running Python or on PATH) for the groups and host variables,
so every inventory format and ``group_vars``/``host_vars`` folder is read as a play reads it, and hands them to the
core (``kuberos.inventory.raw_inventory``). Inside a play the ``fleet_inventory`` filter does the same from
``groups`` and ``hostvars``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import raw_inventory


class InventoryReadError(ValueError):
    """The inventory cannot be read; the message names the path and why."""


def _command() -> str:
    beside = os.path.join(os.path.dirname(sys.executable), "ansible-inventory")
    return beside if os.path.exists(beside) else (shutil.which("ansible-inventory") or "ansible-inventory")


def _members(listing: dict, group: str, seen: frozenset = frozenset()) -> set[str]:
    """A group's hosts, those of its descendants included (as Ansible's group.get_hosts())."""
    entry = listing.get(group) or {}
    hosts = set(entry.get("hosts") or ())
    for child in entry.get("children") or ():
        if child not in seen:
            hosts |= _members(listing, child, seen | {group})
    return hosts


def read_inventory(path: str, timeout: float = 120.0) -> dict:
    """The plain-data resource model of the inventory at ``path`` (not yet validated: ``load_inventory`` does)."""
    if not os.path.exists(path):
        raise InventoryReadError(f"{path}: no such inventory file or directory")
    try:
        done = subprocess.run(
            [_command(), "--list", "-i", path], capture_output=True, text=True, timeout=timeout, check=False,
            env={**os.environ, "ANSIBLE_INVENTORY_UNPARSED_FAILED": "true", "ANSIBLE_NOCOLOR": "1"},
        )  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as error:
        raise InventoryReadError(f"{path}: ansible-inventory did not run: {error}") from error
    if done.returncode != 0:
        reason = " ".join(done.stderr.split())[-600:] or f"exit code {done.returncode}"
        raise InventoryReadError(f"{path}: not a usable inventory: {reason}")
    try:
        listing = json.loads(done.stdout)
    except ValueError as error:
        raise InventoryReadError(f"{path}: ansible-inventory printed no JSON: {error}") from error
    hostvars = (listing.get("_meta") or {}).get("hostvars") or {}
    groups = {name: sorted(_members(listing, name)) for name in listing if name != "_meta"}
    return raw_inventory(groups, {host: hostvars.get(host) or {} for host in {h for g in groups.values() for h in g}})
