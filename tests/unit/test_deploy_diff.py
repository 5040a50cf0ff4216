"""kuberos/diff.py: objects cleaned as people compare them, one diff per object, and the per-module summary."""

from __future__ import annotations

import base64
import copy
import gzip

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.diff import (
    change_summary,
    clean_object,
    deployment_changes,
    object_diff,
    parameter_changes,
    summary_text,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import (
    DiscoveryServer,
    Instance,
    Placement,
)


def deployment(name="app-planner-fetch-1", image="x/planner:1", env=None, node="edge-1", version=None):
    labels = {"kuberos.io/instance": name, **({"kuberos.io/version": version} if version else {})}
    return {
        "apiVersion": "apps/v1",
        "kind": "Deployment",
        "metadata": {
            "name": name,
            "namespace": "kuberos-f",
            "labels": labels,
            "managedFields": [{"manager": "kuberos"}],
            "resourceVersion": "42",
            "generation": 3,
            "uid": "u-1",
            "creationTimestamp": "2026-01-01T00:00:00Z",
        },
        "spec": {
            "strategy": {"type": "RollingUpdate"},
            "template": {
                "spec": {
                    "nodeSelector": {"device.kuberos.io/hostname": node},
                    "containers": [
                        {
                            "name": "planner",
                            "image": image,
                            "args": ["run"],
                            "env": [{"name": k, "value": v} for k, v in (env or {"LOG_LEVEL": "info"}).items()],
                            "resources": {"requests": {"cpu": "1", "memory": "1Gi"}},
                        }
                    ],
                }
            },
        },
        "status": {"replicas": 1},
    }


def params(values):
    import yaml

    text = yaml.safe_dump({"/**": {"ros__parameters": values}})
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": "app-planner-params", "namespace": "kuberos-f"},
        "data": {"params.yaml": text},
    }


def instance(robot, node, module="planner"):
    return Instance(f"app-{module}-{robot}", "app", "f", "kuberos-f", module, node, "edge", (robot,), "", 1.0, 100, 1, 0)


def test_clean_object_drops_server_bookkeeping_and_encodes_blobs_as_digests():
    blob = base64.b64encode(gzip.compress(b'{"a": 1}', mtime=0)).decode()
    record = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": "r", "namespace": "n", "resourceVersion": "1", "managedFields": []},
        "data": {"k": "v"},
        "binaryData": {"placement.json.gz": blob},
    }
    clean = clean_object(record)
    assert clean["metadata"] == {"name": "r", "namespace": "n"}
    assert clean["binaryData"]["placement.json.gz"].startswith("<28 bytes, sha256:")
    assert clean_object(deployment())["metadata"].keys() == {"name", "namespace", "labels"}
    assert "status" not in clean_object(deployment())
    secret = clean_object({"kind": "Secret", "metadata": {"name": "s"}, "data": {"tls.key": base64.b64encode(b"key").decode()}})
    assert secret["data"]["tls.key"].startswith("<3 bytes, sha256:")  # a key is never shown


def test_object_diff_none_when_only_bookkeeping_differs():
    live = deployment()
    dry = copy.deepcopy(live)
    dry["metadata"]["resourceVersion"] = "43"
    dry["status"] = {"replicas": 2}
    assert object_diff(live, dry) is None
    dry["spec"]["template"]["spec"]["containers"][0]["image"] = "x/planner:2"
    entry = object_diff(live, dry)
    assert entry["before_header"].endswith("(live)") and entry["after_header"].endswith("(server dry run)")
    assert "image: x/planner:1" in entry["before"] and "image: x/planner:2" in entry["after"]
    assert "managedFields" not in entry["before"] + entry["after"]
    new = object_diff(None, dry)
    assert new["before"] == "" and new["before_header"].endswith("(absent)") and new["after_header"].endswith("(new)")
    assert object_diff(live, None)["after_header"].endswith("(removed)")


@pytest.mark.parametrize(
    ("before", "after", "expected"),
    [
        ({}, {"image": "x/planner:2"}, ["image x/planner:1 -> x/planner:2"]),
        ({}, {"env": {"LOG_LEVEL": "debug"}}, ["env LOG_LEVEL info -> debug"]),
        ({}, {"env": {"LOG_LEVEL": "info", "NEW": "1"}}, ["env +NEW=1"]),
        ({}, {"version": "0.2.0"}, ["version - -> 0.2.0"]),
        ({}, {"node": "edge-2"}, []),  # a move is said as a move, not as a change
    ],
)
def test_deployment_changes(before, after, expected):
    assert deployment_changes(deployment(**before), deployment(**after)) == expected


def test_parameter_changes():
    assert parameter_changes(params({"a": 1, "b": 2}), params({"a": 1, "b": 3, "c": 4})) == ["parameters b 2 -> 3, +c=4"]
    assert parameter_changes(params({"a": 1}), params({"a": 1})) == []


def test_change_summary_names_moves_starts_stops_and_changes():
    old = Placement(
        [instance("fetch-1", "edge-1"), instance("fetch-2", "edge-2"), instance("fetch-1", "edge-1", module="driver")],
        {"f": [DiscoveryServer("f", "kuberos-f", 0, "kuberos-discovery-0", "edge-1", "edge", 11811, "")]},
        [{"name": "app", "fleet": "f", "namespace": "kuberos-f"}],
    )
    new = Placement(
        [instance("fetch-1", "cloud-1"), instance("fetch-2", "edge-2"), instance("fetch-3", "edge-1")],
        {"f": [DiscoveryServer("f", "kuberos-f", 0, "kuberos-discovery-0", "edge-2", "edge", 11811, "")]},
        [{"name": "app", "fleet": "f", "namespace": "kuberos-f"}],
    )
    pairs = {
        ("Deployment", "kuberos-f", "app-planner-fetch-2"): (
            deployment("app-planner-fetch-2"),
            deployment("app-planner-fetch-2", image="x/planner:2"),
        ),
        ("ConfigMap", "kuberos-f", "app-planner-params"): (params({"a": 1}), params({"a": 1})),
    }
    rows = change_summary({"app": old}, new, pairs)
    got = {(r["module"], r["robot"], r["action"], r["from"], r["to"]) for r in rows}
    assert got == {
        ("planner", "fetch-1", "move", "edge-1", "cloud-1"),
        ("planner", "fetch-2", "change", "edge-2", "edge-2"),
        ("planner", "fetch-3", "start", "", "edge-1"),
        ("driver", "fetch-1", "stop", "edge-1", ""),
        ("kuberos-discovery-0", "fleet f", "move", "edge-1", "edge-2"),
    }
    text = summary_text(rows, [], {"changed": 2}, check_mode=True)
    assert "app/planner (fetch-1): moves edge-1 -> cloud-1" in text
    assert "app/planner (fetch-2): changes: image x/planner:1 -> x/planner:2" in text
    assert "app/driver (fetch-1): stops on edge-1" in text
    assert text.startswith("What the deploy would change (check mode: nothing written):")
    # Not deployed before: every module starts.
    assert {r["action"] for r in change_summary({"app": None}, new, {})} == {"start"}
    assert "no module moves" in summary_text([], [], {}, check_mode=False)


def test_summary_names_what_the_cluster_refused():
    text = summary_text([], [], {"unchanged": 3}, check_mode=True, refused={"Deployment n/a": "forbidden by policy p"})
    assert text.splitlines()[-1] == "  refused by the cluster's dry run: Deployment n/a: forbidden by policy p"


def test_object_diff_compares_data_before_it_dumps(monkeypatch):
    """A re-run compares hundreds of unchanged objects: they are compared as data and never dumped to YAML."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import diff

    dumped = []
    monkeypatch.setattr(diff, "dump_object", lambda obj: dumped.append(obj) or repr(obj))
    live = {"kind": "ConfigMap", "apiVersion": "v1", "metadata": {"name": "a", "namespace": "n"}, "data": {"x": "1"}}
    reordered = {"data": {"x": "1"}, "metadata": {"namespace": "n", "name": "a"}, "apiVersion": "v1", "kind": "ConfigMap"}
    assert object_diff(live, reordered) is None and dumped == []
    changed = {**live, "data": {"x": "2"}}
    entry = object_diff(live, changed)
    assert entry is not None and len(dumped) == 2 and entry["after"] != entry["before"]
