"""deploy.yml --check --diff against the real local control plane: what the cluster would change, per object (a
server-side dry run diffed against the live object) and first per module of each robot; check mode writes nothing.

Proves: nothing changed shows no diff; the same spec under another file name shows no new object (only the record's
and the revision's source); an edit (one module's image, one module moved by a preference change, one module
removed) shows exactly the objects it changes, new and removed, readable (no managedFields, no base64 blobs), with a
summary first that names module, robots and nodes; no object's resourceVersion moves in check mode; the diff runs
outside check mode too (--diff on a real deploy), and afterwards the cluster matches the spec.
"""

from __future__ import annotations

import os
import re
import shutil

import pytest
from helpers import ROOT, deployments_denied, without_module

pytestmark = pytest.mark.cluster

NAMESPACE = "kuberos-test-fleet"
DIFF_TASK = "TASK [kuberos.platform.rosdeployment : Validate, place, render, dry-run, apply, prune and wait]"
HEADER = re.compile(r"^--- before: (\S+) (\S+) \((live|absent)\)\n\+\+\+ after: \S+ \S+ \((server dry run|new|removed)\)$", re.M)
BLOB = re.compile(r"[A-Za-z0-9+/=]{80,}")  # a base64 run as long as a line


def diff_section(result) -> str:
    """What the diff task printed: its summary, then one diff per object."""
    out = result.stdout
    assert DIFF_TASK in out, out[-6000:]
    section = out[out.index(DIFF_TASK) + len(DIFF_TASK) :]
    ends = [i for i in (section.find("\nTASK ["), section.find("\nPLAY RECAP")) if i >= 0]  # a failed task ends the play
    return section[: min(ends)]


def headers(section: str) -> dict[tuple[str, str], str]:
    """(kind, namespace/name) -> live|absent|removed for every object diff shown."""
    found = {}
    for kind, name, before, after in HEADER.findall(section):
        found[(kind, name)] = "removed" if after == "removed" else before
    return found


def live_versions(cluster) -> dict:
    """resourceVersion of every object in the fleet's namespace (and of the namespace)."""
    core, apps, _discovery = cluster.clients()
    versions = {("Namespace", NAMESPACE): core.read_namespace(NAMESPACE).metadata.resource_version}
    for d in apps.list_namespaced_deployment(NAMESPACE).items:
        versions[("Deployment", d.metadata.name)] = d.metadata.resource_version
    for c in core.list_namespaced_config_map(NAMESPACE).items:
        versions[("ConfigMap", c.metadata.name)] = c.metadata.resource_version
    for s in core.list_namespaced_service(NAMESPACE).items:
        versions[("Service", s.metadata.name)] = s.metadata.resource_version
    return versions


@pytest.fixture
def deployed(cluster, tmp_path):
    spec = tmp_path / "pick-and-place.yml"
    shutil.copy(os.path.join(ROOT, "examples", "pick-and-place.yml"), spec)
    first = cluster.deploy(spec, tmp_path / "render")
    assert first.returncode == 0, first.stdout[-6000:] + first.stderr[-2000:]
    yield spec
    cluster.undeploy(spec)


def test_check_diff_shows_what_the_cluster_would_change_and_writes_nothing(cluster, deployed, tmp_path):
    spec = deployed
    render = tmp_path / "render"
    core, _apps, _discovery = cluster.clients()
    # Revisions count on from what earlier tests of this cluster deployed under the same name.
    revision = int(core.read_namespaced_config_map("kuberos-record-pick-and-place", NAMESPACE).data["revision"])

    # Nothing changed: no object diff, the summary says so.
    same = cluster.deploy(spec, render, "--check", "--diff")
    assert same.returncode == 0, same.stdout[-6000:]
    section = diff_section(same)
    assert headers(section) == {}, section
    assert "no module moves, starts, stops or changes" in same.stdout
    assert "objects: 0 changed, 0 new, 0 removed" in same.stdout

    # The same spec under another file name (and so another render directory): no new object, no module changes. The
    # record and its revision would note the new source path, nothing else.
    other = tmp_path / "renamed-copy.yml"
    shutil.copy(spec, other)
    renamed = cluster.deploy(other, tmp_path / "render-renamed", "--check", "--diff")
    assert renamed.returncode == 0, renamed.stdout[-6000:]
    section = diff_section(renamed)
    shown = headers(section)
    assert set(shown) <= {
        ("ConfigMap", f"{NAMESPACE}/kuberos-record-pick-and-place"),
        ("ConfigMap", f"{NAMESPACE}/kuberos-rev-pick-and-place-{revision}"),
    }, section
    assert set(shown.values()) <= {"live"}, section
    assert "no module moves, starts, stops or changes" in renamed.stdout
    changed_lines = [line for line in section.splitlines() if re.match(r"^[-+]\s", line)]
    assert changed_lines, section
    # The source path is kept in the record and the revision, and in the record's placement (its deployments' source).
    assert [line for line in changed_lines if not re.match(r"^[-+]\s+(source|placement\.json\.gz):", line)] == [], section

    # An edit: a new planner image, the task coordinator prefers the cloud now, perception is dropped.
    text = spec.read_text().replace("pnp-planner:0.1", "pnp-planner:0.2")
    text = text.replace("  preference: edge\n  strategy: shared", "  preference: cloud\n  strategy: shared")
    text = without_module(text, "perception")
    spec.write_text(text)
    before = live_versions(cluster)
    edited = cluster.deploy(spec, render, "--check", "--diff")
    assert edited.returncode == 0, edited.stdout[-6000:]
    assert live_versions(cluster) == before  # check mode wrote nothing
    section = diff_section(edited)

    # The summary comes first and names module, robots and nodes.
    summary = section[: section.index("--- before:")]
    assert "What the deploy would change (check mode: nothing written):" in summary
    assert (
        "pick-and-place/motion-planner (fetch-1, fetch-2): changes: "
        "image ghcr.io/kuberos/pnp-planner:0.1 -> ghcr.io/kuberos/pnp-planner:0.2" in summary
    ), summary
    for robot in ("fetch-1", "fetch-2"):
        assert re.search(rf"pick-and-place/perception \({robot}\): stops on edge-\d", summary), summary
        assert re.search(rf"pick-and-place/task-coordinator \({robot}\): moves edge-\d -> cloud-\d", summary), summary
    # perception's 2 instances go, the coordinator moves.
    assert "record kuberos-test-fleet/kuberos-record-pick-and-place: updated, placement of 3 instances changed" in summary

    # Exactly the objects the edit changes: the planners, the coordinator, the record and a new revision; perception's
    # Deployments and parameters are removed. Nothing else.
    shown = headers(section)
    expected = {
        ("ConfigMap", f"{NAMESPACE}/kuberos-record-pick-and-place"): "live",
        ("ConfigMap", f"{NAMESPACE}/kuberos-rev-pick-and-place-{revision + 1}"): "absent",
        ("Deployment", f"{NAMESPACE}/pick-and-place-motion-planner-fetch-1"): "live",
        ("Deployment", f"{NAMESPACE}/pick-and-place-motion-planner-fetch-2"): "live",
        ("Deployment", f"{NAMESPACE}/pick-and-place-task-coordinator-shared-0"): "live",
        ("Deployment", f"{NAMESPACE}/pick-and-place-perception-fetch-1"): "removed",
        ("Deployment", f"{NAMESPACE}/pick-and-place-perception-fetch-2"): "removed",
        ("ConfigMap", f"{NAMESPACE}/pick-and-place-perception-params"): "removed",
    }
    assert shown == expected, section
    # Readable: the image line itself, no server bookkeeping, no encoded blobs.
    assert re.search(r"^-\s+image: ghcr.io/kuberos/pnp-planner:0.1$", section, re.M), section
    assert re.search(r"^\+\s+image: ghcr.io/kuberos/pnp-planner:0.2$", section, re.M), section
    for noise in ("managedFields", "resourceVersion", "creationTimestamp", "uid:", "status:"):
        assert noise not in section, noise
    assert not BLOB.search(section), BLOB.search(section).group(0)[:100]
    # The render directory's own diff is not shown when a cluster is there to diff against.
    assert "--- before: manifests/" not in edited.stdout

    # Without --diff, check mode still prints the summary, as its own task.
    quiet = cluster.deploy(spec, render, "--check")
    assert quiet.returncode == 0, quiet.stdout[-6000:]
    assert "--- before:" not in quiet.stdout
    assert "pick-and-place/motion-planner (fetch-1, fetch-2): changes: image" in quiet.stdout
    assert live_versions(cluster) == before

    # --diff on a real deploy shows what is being applied; afterwards nothing is left to change.
    applied = cluster.deploy(spec, render, "--diff")
    assert applied.returncode == 0, applied.stdout[-6000:]
    assert "What the deploy changes:" in diff_section(applied)
    assert headers(diff_section(applied)) == expected
    again = cluster.deploy(spec, render, "--check", "--diff")
    assert again.returncode == 0, again.stdout[-6000:]
    assert headers(diff_section(again)) == {}, diff_section(again)


def test_an_object_the_cluster_refuses_is_named_in_the_summary(cluster, deployed, tmp_path):
    """A policy refuses the new planner image: the diff names the refused objects and what the cluster said, the
    deploy's own dry run stops the run, nothing is written."""
    import time

    _core, apps, _discovery = cluster.clients()
    expression = "object.spec.template.spec.containers.all(c, !c.image.endsWith(':0.3'))"
    refusal = "images of version 0.3 are not allowed in this cluster"
    with deployments_denied(apps.api_client, "no-planner-0-3", expression, refusal):
        deployed.write_text(deployed.read_text().replace("pnp-planner:0.1", "pnp-planner:0.3"))
        before = live_versions(cluster)
        deadline = time.monotonic() + 30
        while True:  # the policy takes a moment to be enforced
            result = cluster.deploy(deployed, tmp_path / "render", "--check", "--diff")
            if result.returncode != 0 or time.monotonic() > deadline:
                break
        assert result.returncode != 0, result.stdout[-6000:]
        section = diff_section(result)
        for robot in ("fetch-1", "fetch-2"):
            assert (
                f"refused by the cluster's dry run: Deployment {NAMESPACE}/pick-and-place-motion-planner-{robot}: " in section
            ), section
        assert "images of version 0.3 are not allowed in this cluster" in section
        assert "nothing was applied" in result.stdout  # the deploy's own dry run stops the run
        assert live_versions(cluster) == before
