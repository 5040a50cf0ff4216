"""A real local control plane for the tests in this folder, started once per session with the
local_cluster playbook on ports of its own (a developer's own local cluster is left alone)."""

from __future__ import annotations

import pytest
from helpers import Cluster


@pytest.fixture(scope="session")
def cluster(tmp_path_factory):
    cluster = Cluster(tmp_path_factory.mktemp("cluster"))
    try:
        started = cluster.start()
        assert started.returncode == 0, started.stdout[-6000:] + started.stderr[-3000:]
        cluster.first_start = started
        yield cluster
    finally:
        cluster.stop(state="absent")
