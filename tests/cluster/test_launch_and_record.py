"""Launch lines and the bounded record against the real local control plane (kwok nodes: no containers run).

Proves: a module of two launch lines is one pod of two containers, each with its literal argv, bound where KubeROS
placed it, its requests adding up to the placement's; the record is format 2 (the document compressed in
binaryData) and reads back; a record of the previous format, applied by deploy's field manager as the previous
deploy did, is replaced by the new one on the next deploy, its ``spec.yaml`` key gone; and the API server counts a
ConfigMap's size as ``record.configmap_bytes`` does (data values plus decoded binaryData, at most 1 MiB).
"""

from __future__ import annotations

import base64
import json
import os
import shutil

import pytest
from helpers import ROOT

pytestmark = pytest.mark.cluster

NAMESPACE = "kuberos-warehouse-fleet"


def _plain(obj) -> dict:
    from kubernetes.client import ApiClient

    return ApiClient().sanitize_for_serialization(obj)


@pytest.fixture
def spec(tmp_path):
    path = tmp_path / "two-fleets.yml"
    shutil.copy(os.path.join(ROOT, "examples", "two-fleets.yml"), path)
    return path


def _apply(core, body: dict, manager: str = "kuberos"):
    return core.patch_namespaced_config_map(
        body["metadata"]["name"], body["metadata"]["namespace"], body, field_manager=manager, force=True,
        _content_type="application/apply-patch+yaml",
    )  # fmt: skip


def test_launch_lines_are_containers_and_the_record_is_bounded(cluster, spec, tmp_path):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.quantities import parse_cpu, parse_memory
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
        fingerprint,
        parse_record,
        restrict_placement,
    )
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments

    core, _apps, _discovery = cluster.clients()
    out = tmp_path / "render"
    first = cluster.deploy(spec, out)
    assert first.returncode == 0, first.stdout[-6000:] + first.stderr[-2000:]
    placement = Placement.from_dict(json.loads((out / "placement.json").read_text()))
    lidar = [i for i in placement.instances if i.module == "lidar-driver"]
    assert lidar
    for inst in lidar:
        (pod,) = [
            p
            for p in core.list_namespaced_pod(NAMESPACE, label_selector=f"kuberos.io/instance={inst.name}").items
            if not p.metadata.deletion_timestamp
        ]
        assert pod.spec.node_name == inst.node and pod.status.phase == "Running"
        assert [(c.name, c.command, c.args) for c in pod.spec.containers] == [
            ("lidar-driver", None, ["ros2", "run", "lidar_driver", "driver_node"]),
            ("lidar-driver-1", None, ["ros2", "run", "lidar_driver", "filter_node"]),
        ]
        requests = [c.resources.requests for c in pod.spec.containers]
        assert sum(parse_cpu(r["cpu"]) for r in requests) == inst.cpu_millis
        assert sum(parse_memory(r["memory"]) for r in requests) == inst.memory_bytes

    text = spec.read_text(encoding="utf-8")
    originals = {d.name: d for d in load_rosdeployments(text, str(spec))}
    configmap = _plain(core.read_namespaced_config_map("kuberos-record-inventory-scan", NAMESPACE))
    assert configmap["data"]["format"] == "2" and "spec.yaml" not in configmap["data"]
    assert "spec.yaml.gz" in configmap["binaryData"]
    record = parse_record(configmap)
    assert fingerprint(record.spec) == fingerprint(originals["inventory-scan"])

    # the previous format, as the previous deploy applied it: the next deploy leaves no trace of it
    legacy = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": configmap["metadata"]["name"], "namespace": NAMESPACE, "labels": configmap["metadata"]["labels"]},
        "data": {**{k: v for k, v in configmap["data"].items() if k != "spec-line"}, "format": "1", "spec.yaml": text},
        "binaryData": {k: v for k, v in configmap["binaryData"].items() if k != "spec.yaml.gz"},
    }
    applied = _plain(_apply(core, legacy))
    assert "spec.yaml.gz" not in applied["binaryData"], "one field manager: its apply replaced the key set"
    old = parse_record(applied)
    assert fingerprint(old.spec) == fingerprint(originals["inventory-scan"])
    assert old.placement.to_dict() == restrict_placement(placement, "inventory-scan").to_dict()
    again = cluster.deploy(spec, out)
    assert again.returncode == 0, again.stdout[-6000:] + again.stderr[-2000:]
    configmap = _plain(core.read_namespaced_config_map("kuberos-record-inventory-scan", NAMESPACE))
    assert configmap["data"]["format"] == "2" and "spec.yaml" not in configmap["data"]
    assert fingerprint(parse_record(configmap).spec) == fingerprint(originals["inventory-scan"])
    removed = cluster.undeploy(spec)
    assert removed.returncode == 0, removed.stdout[-4000:]


def test_the_api_server_counts_a_configmap_as_configmap_bytes_does(cluster):
    from kubernetes.client.exceptions import ApiException

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import CONFIGMAP_LIMIT, configmap_bytes

    core, _apps, _discovery = cluster.clients()

    def accepted(data: dict, binary: dict) -> bool:
        body = {"apiVersion": "v1", "kind": "ConfigMap", "metadata": {"name": "size-probe"}, "data": data, "binaryData": binary}
        try:
            core.create_namespaced_config_map("default", body, dry_run="All")
        except ApiException as exc:
            assert exc.status == 422, exc.body
            return False
        return True

    half = CONFIGMAP_LIMIT // 2
    for extra in (0, 1):
        data = {"a": "x" * half}
        binary = {"b.gz": base64.b64encode(b"\0" * (CONFIGMAP_LIMIT - half + extra)).decode()}
        assert configmap_bytes({"data": data, "binaryData": binary}) == CONFIGMAP_LIMIT + extra
        assert accepted(data, binary) == (extra == 0), extra
