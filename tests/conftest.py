"""Shared fixtures: the embedded inventory as the scheduler sees it."""

from __future__ import annotations

import pytest
from helpers import ROOT, inventory_raw


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
