"""The deployment record stays bounded: its own document only, compressed, and refused when it would not fit.

Records written by the previous format (the whole spec file as text in ``data``) are still read: clusters that run
them keep working with a new controller and rollouts.
"""

from __future__ import annotations

import base64
import copy
import functools
import gzip
import json
import random

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import (
    CONFIGMAP_LIMIT,
    RECORD_BUDGET,
    RECORD_LABEL,
    build_records,
    configmap_bytes,
    fingerprint,
    parse_record,
    parse_revision,
    restrict_placement,
    spec_text_of,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments

DOC = """\
metadata:
  name: {name}
  targetFleet: {fleet}
rosModules:
- name: planner
  image: ghcr.io/example/planner:1.0
  launch: [ros2 launch planner planner.launch.py]
  preference: cloud
  resources: {{cpu: 100m, memory: 64Mi}}
"""


def records_of(text: str, source: str, inventory, raw, catalog=None) -> list[dict]:
    deployments = load_rosdeployments(text, source, catalog=catalog)
    placement = place_modules(deployments, inventory)
    return build_records(text, source, deployments, placement, raw, RenderOptions(), "kuberos", {}, catalog)


def only_records(objects: list[dict]) -> dict[str, dict]:
    return {o["data"]["deployment"]: o for o in objects if RECORD_LABEL in o["metadata"]["labels"]}


def legacy_record(text: str, source: str, dep, placement, raw: dict) -> dict:
    """A record exactly as the previous format (1) wrote it: the whole file's text in data."""

    def pack(data) -> str:
        return base64.b64encode(gzip.compress(json.dumps(data, sort_keys=True, separators=(",", ":")).encode(), mtime=0)).decode()

    options = {"cluster_domain": "cluster.local", "discovery_image": "ros:jazzy-ros-base", "image_pull_policy": "IfNotPresent"}
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": f"kuberos-record-{dep.name}", "namespace": "kuberos-test-fleet", "resourceVersion": "7"},
        "data": {
            "format": "1",
            "writer": "controller",
            "deployment": dep.name,
            "revision": "3",
            "revision-hash": fingerprint(dep),
            "source": source,
            "spec.yaml": text,
            "options.json": json.dumps({**options, "field_manager": "kuberos"}, sort_keys=True),
            "rollout.json": json.dumps({"revision": 4}),
        },
        "binaryData": {
            "inventory.json.gz": pack(raw),
            "placement.json.gz": pack(restrict_placement(placement, dep.name).to_dict()),
        },
    }


def test_a_record_of_the_previous_format_still_reads(root, local_inventory, local_raw):
    path = f"{root}/examples/two-fleets.yml"
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    deployments = load_rosdeployments(text, "examples/two-fleets.yml")
    placement = place_modules(deployments, local_inventory)
    second = deployments[1]
    record = parse_record(legacy_record(text, "examples/two-fleets.yml", second, placement, local_raw))
    assert record.deployment == second.name and fingerprint(record.spec) == fingerprint(second)
    assert [d.name for d in record.deployments] == [second.name]
    assert record.placement.to_dict() == restrict_placement(placement, second.name).to_dict()
    assert record.inventory_raw == local_raw and record.field_manager == "kuberos"
    assert (record.revision, record.writer, record.rollout, record.resource_version) == (3, "controller", {"revision": 4}, "7")


def test_a_revision_of_the_previous_format_still_reads(root, local_inventory, local_raw):
    path = f"{root}/examples/pick-and-place.yml"
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    (dep,) = load_rosdeployments(text, "examples/pick-and-place.yml")
    legacy = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": "kuberos-rev-pick-and-place-2", "namespace": "kuberos-test-fleet"},
        "data": {"format": "1", "deployment": dep.name, "revision": "2", "cause": "deploy", "spec.yaml": text},
    }
    number, cause, read, spec, catalog = parse_revision(legacy)
    assert (number, cause, spec, catalog) == (2, "deploy", text, None) and fingerprint(read) == fingerprint(dep)


def test_each_record_keeps_only_its_own_document_with_its_lines(root, local_inventory, local_raw):
    path = f"{root}/examples/two-fleets.yml"
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    objects = records_of(text, "examples/two-fleets.yml", local_inventory, local_raw)
    originals = {d.name: d for d in load_rosdeployments(text, "examples/two-fleets.yml")}
    records = only_records(objects)
    assert sorted(records) == sorted(originals)
    for name, configmap in records.items():
        assert configmap["data"]["format"] == "2" and "spec.yaml" not in configmap["data"]
        kept = spec_text_of(configmap)
        assert [d.name for d in load_rosdeployments(kept, "record")] == [name], "one document, its own"
        parsed = parse_record(configmap)
        assert fingerprint(parsed.spec) == fingerprint(originals[name])
        # problems read back from a record name the lines of the file it was deployed from
        assert parsed.spec.lines == originals[name].lines
        assert int(configmap["data"]["spec-line"]) == originals[name].lines[""]  # where the document starts
    revisions = [o for o in objects if RECORD_LABEL not in o["metadata"]["labels"]]
    for revision in revisions:
        _number, _cause, dep, kept, _catalog = parse_revision(revision)
        assert fingerprint(dep) == fingerprint(originals[dep.name]) and "---" not in kept.strip()


def test_forty_documents_give_forty_records_of_one_document_each(local_inventory, local_raw):
    one = DOC.format(name="app-0", fleet="warehouse-fleet")
    forty = "---\n".join(DOC.format(name=f"app-{i}", fleet="warehouse-fleet") for i in range(40))
    alone = only_records(records_of(one, "one.yml", local_inventory, local_raw))["app-0"]
    records = only_records(records_of(forty, "forty.yml", local_inventory, local_raw))
    assert len(records) == 40
    # the last document's record holds its own document, not the 39 before it (only blank lines stand for them)
    last = records["app-39"]
    assert spec_text_of(last).strip() == one.replace("app-0", "app-39").strip()
    assert configmap_bytes(records["app-0"]) <= configmap_bytes(alone) + 64
    assert configmap_bytes(last) < configmap_bytes(alone) + 200


def test_catalog_entries_are_kept_per_deployment(root, local_inventory, local_raw):
    catalog = load_catalog(f"{root}/inventories/local/catalog")
    text = "\n---\n".join(
        [
            DOC.format(name="plain", fleet="test-fleet"),
            "metadata: {name: perceiving, targetFleet: test-fleet}\n"
            "rosModules:\n- {name: perception, module: pnp-perception@^0.1}\n",
        ]
    )
    records = only_records(records_of(text, "mixed.yml", local_inventory, local_raw, catalog))
    assert "catalog.json.gz" not in records["plain"]["binaryData"]
    kept = parse_record(records["perceiving"])
    assert [(m.catalog_module, m.version) for m in kept.spec.modules] == [("pnp-perception", "0.1.0")]


@functools.cache
def incompressible_comments(size: int, seed: int = 1) -> str:
    generator = random.Random(seed)
    alphabet = [chr(c) for c in range(0x21, 0x7F)]
    lines, total = [], 0
    while total < size:
        line = "# " + "".join(generator.choice(alphabet) for _ in range(98))
        lines.append(line)
        total += len(line) + 1
    return "\n".join(lines) + "\n"


def oversized_spec() -> str:
    """Two documents within the spec size limit; the second carries 1 MB of comments that gzip cannot shrink."""
    small = DOC.format(name="small", fleet="test-fleet")
    big = DOC.format(name="huge", fleet="warehouse-fleet") + incompressible_comments(1_000_000)
    return small + "---\n" + big


def test_a_record_that_would_not_fit_is_refused_naming_file_line_and_deployment(local_inventory, local_raw):
    text = oversized_spec()
    assert len(text.encode()) <= 1024 * 1024, "within the spec size limit"
    deployments = load_rosdeployments(text, "big.yml")
    placement = place_modules(deployments, local_inventory)
    with pytest.raises(SpecError) as raised:
        build_records(text, "big.yml", deployments, placement, local_raw, RenderOptions(), "kuberos")
    (problem,) = raised.value.problems
    assert problem.source == "big.yml (document 2)" and problem.line == 11  # the line after the '---'

    message = str(raised.value)
    assert "big.yml (document 2):11:" in message and "'huge'" in message and "kuberos-record-huge" in message
    assert f"over the {RECORD_BUDGET:,}" in message and "spec document (gzip)" in message


def test_a_large_spec_that_compresses_well_fits(local_inventory, local_raw):
    note = "the planner runs on the cloud tier, with a latency budget of 200 ms and 2 CPUs"
    notes = "".join(f"# note {i}: {note}\n" for i in range(10_500))
    text = DOC.format(name="ordinary", fleet="warehouse-fleet") + notes
    assert 0.9 * 1024 * 1024 < len(text.encode()) <= 1024 * 1024
    record = only_records(records_of(text, "ordinary.yml", local_inventory, local_raw))["ordinary"]
    assert configmap_bytes(record) < 64 * 1024 < RECORD_BUDGET < CONFIGMAP_LIMIT
    assert spec_text_of(record) == text, "the document as written, comments and all"
    assert parse_record(record).spec.name == "ordinary"


def test_a_document_that_leans_on_a_yaml_directive_is_kept_written_out_again(local_inventory, local_raw):
    text = "%TAG !k! tag:yaml.org,2002:\n---\n" + DOC.format(name="!k!str tagged", fleet="warehouse-fleet")
    (record,) = only_records(records_of(text, "tagged.yml", local_inventory, local_raw)).values()
    kept = spec_text_of(record)
    assert "%TAG" not in kept and "!k!" not in kept
    assert parse_record(record).spec.name == "tagged"


def test_the_record_is_deterministic_and_each_record_reads_back_alone(root, local_inventory, local_raw):
    path = f"{root}/examples/two-fleets.yml"
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    first = records_of(text, "examples/two-fleets.yml", local_inventory, local_raw)
    again = records_of(text, "examples/two-fleets.yml", local_inventory, local_raw)
    assert first == again, "applied twice, nothing changes"
    for configmap in only_records(copy.deepcopy(first)).values():
        assert parse_record(configmap).spec.name == configmap["data"]["deployment"]


def test_the_render_module_refuses_it_before_writing_anything(tmp_path, local_inventory, local_raw, monkeypatch):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import record
    from ansible_collections.kuberos.platform.plugins.modules import rosdeployment_render

    monkeypatch.setattr(record, "RECORD_BUDGET", 20_000)  # a small budget: a small spec goes over it
    text = DOC.format(name="small", fleet="test-fleet") + "---\n" + DOC.format(name="huge", fleet="warehouse-fleet")
    text += incompressible_comments(30_000)
    spec = tmp_path / "big.yml"
    spec.write_text(text, encoding="utf-8")
    deployments = load_rosdeployments(text, str(spec))
    dest = tmp_path / "rendered"
    params = {
        "src": str(spec), "placement": place_modules(deployments, local_inventory).to_dict(), "dest": str(dest),
        "inventory": local_raw, "field_manager": "kuberos", "catalog": None, "revisions": {},
        "cluster_domain": "cluster.local", "discovery_image": "ros:jazzy-ros-base", "bridge_image": "bridge:1",
    }  # fmt: skip

    class Module:
        check_mode = False
        _diff = False

        def __init__(self):
            self.params = params

    expected = r"big.yml \(document 2\):11: the deployment 'huge' needs a ConfigMap kuberos-record-huge"
    with pytest.raises(SpecError, match=expected):
        rosdeployment_render.run(Module())
    assert not dest.exists()


def test_a_rollback_records_the_kept_document_again_unchanged(root, local_inventory, local_raw):
    """A rollback builds the new record from a revision's text: the same document, at the same line."""
    path = f"{root}/examples/two-fleets.yml"
    with open(path, encoding="utf-8") as handle:
        text = handle.read()
    objects = records_of(text, "examples/two-fleets.yml", local_inventory, local_raw)
    revision = next(o for o in objects if o["metadata"]["name"] == "kuberos-rev-inventory-scan-1")
    _number, _cause, dep, kept, _catalog = parse_revision(revision)
    placement = place_modules([dep], local_inventory)
    again = build_records(
        kept, "examples/two-fleets.yml", [dep], placement, local_raw, RenderOptions(), "kuberos", {}, None, "rollback to 1"
    )
    record = only_records(again)["inventory-scan"]
    assert spec_text_of(record) == kept and record["data"]["spec-line"] == revision["data"]["spec-line"] != "1"


def test_the_revision_hash_is_what_a_deployment_asks_for_not_how_its_document_is_written():
    """Each deployment keeps its document's text from the one parse (for the record); a comment or a moved line
    changes that text, not the revision: a deploy of the same request must not start a new one."""
    import os

    from helpers import ROOT

    with open(os.path.join(ROOT, "examples", "listing1.yml"), encoding="utf-8") as handle:
        text = handle.read()
    (plain,) = load_rosdeployments(text, "a.yml")
    (commented,) = load_rosdeployments("# a comment above\n\n" + text, "b.yml")
    assert plain.document != commented.document and commented.document.startswith("\n\n\n")
    assert fingerprint(plain) == fingerprint(commented)
