"""Shared fixtures: the embedded inventory as the scheduler sees it; the two lanes of ``make test``."""

from __future__ import annotations

import lanes
import pytest
from helpers import ROOT, inventory_raw

# `make test` runs two lanes side by side (pytest-xdist: -n 2 --dist loadgroup; tests/lanes.py). The host lane has every test that
# changes this machine (network namespaces, links, routes, mounts, cgroups, sysctls, containerds, lab machines) or
# runs DDS on its network; they run one after another, as the host snapshots they compare require. The API lane has
# the rest: pure code, lint, and the tests against the kwok control plane, which only listens on loopback ports.
HOST_LANE_MARKERS = ("host", "molecule", "site", "real_nodes", "ros", "sim")


def pytest_itemcollected(item):
    lane = "host" if any(item.get_closest_marker(name) for name in HOST_LANE_MARKERS) else "api"
    item.add_marker(pytest.mark.xdist_group(lane))


def pytest_configure(config):
    lanes.configure(config)


def pytest_unconfigure(config):
    lanes.unconfigure(config)


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's worker reports its collection
def pytest_collection_finish(session):
    lanes.collection_finished(session)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    return lanes.make_scheduler(config, log)


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
