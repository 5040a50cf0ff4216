"""The two lanes of ``make test``: pytest-xdist's ``-n 2 --dist loadgroup``, grouped by each test's ``xdist_group``.

tests/conftest.py gives every test a group: ``host`` for the tests that change this machine (they run one after
another in one worker), ``api`` for the rest (the other worker). pytest-xdist 3.8 groups tests by appending the group
to each test's node id in its workers, which pytest 9 ignores (a node's id no longer comes from the attribute it
sets), so its ``loadgroup`` alone would run any test in any worker. Here the first worker writes each test's group to
a file the controller names (``KUBEROS_TEST_GROUPS``), before it reports its collection, and the controller's
scheduler (pytest-xdist's own scope scheduler) reads the groups from it: one group, one worker.
"""

from __future__ import annotations

import json
import os
import tempfile

ENV = "KUBEROS_TEST_GROUPS"


def group_of(item) -> str:
    """A test's group: its xdist_group marker's name; a test without one is a group of its own."""
    marker = item.get_closest_marker("xdist_group")
    return str(marker.args[0]) if marker and marker.args else item.nodeid


def _grouping(config) -> bool:
    return (
        not hasattr(config, "workerinput")
        and bool(config.getoption("numprocesses", None))
        and (config.getoption("dist", "no") == "loadgroup")
    )


def configure(config) -> None:
    """In the controller of a ``--dist loadgroup`` run: the file the first worker writes the groups to."""
    if _grouping(config):
        handle, path = tempfile.mkstemp(prefix="kuberos-test-groups-", suffix=".json")
        os.close(handle)
        os.environ[ENV] = config.kuberos_groups_file = path


def unconfigure(config) -> None:
    path = getattr(config, "kuberos_groups_file", "")
    if path and os.path.exists(path):
        os.remove(path)


def collection_finished(session) -> None:
    """In the first worker: every collected test's group, written whole before the worker reports its collection.
    With ``KUBEROS_LANES_REPORT`` set, every test's file and group are printed (tests/unit/test_lanes.py)."""
    if os.environ.get("KUBEROS_LANES_REPORT"):
        for item in session.items:
            print(f"lane {item.nodeid.split('::')[0]} {group_of(item)}")
    workerinput = getattr(session.config, "workerinput", None)
    path = os.environ.get(ENV)
    if not path or not workerinput or workerinput.get("workerid") != "gw0":
        return
    partial = f"{path}.partial"
    with open(partial, "w", encoding="utf-8") as handle:
        json.dump({item.nodeid: group_of(item) for item in session.items}, handle)
    os.replace(partial, path)


def make_scheduler(config, log):
    """pytest-xdist's scope scheduler with the groups as scopes (None: xdist's own scheduler)."""
    if config.getoption("dist", "no") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        groups: dict[str, str] | None = None

        def _split_scope(self, nodeid: str) -> str:
            if self.groups is None:
                with open(os.environ[ENV], encoding="utf-8") as handle:
                    self.groups = json.load(handle)
            return self.groups.get(nodeid, nodeid)

    return GroupScheduling(config, log)
