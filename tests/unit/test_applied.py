"""An apply that would change nothing is known without a dry run (kuberos.applied): the digest of what was applied,
every field of it still in place, KubeROS holding its fields. Anything else asks the API server."""

from __future__ import annotations

import copy

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.applied import (
    APPLIED,
    applied_hash,
    holds,
    stamped,
    unchanged,
)

CONFIG = {
    "apiVersion": "apps/v1",
    "kind": "Deployment",
    "metadata": {"name": "planner", "namespace": "kuberos-f", "labels": {"app.kubernetes.io/managed-by": "kuberos"}},
    "spec": {"replicas": 1, "template": {"spec": {"containers": [{"name": "planner", "image": "r/p:1", "args": ["a"]}]}}},
}


def live_after_apply(config=CONFIG, manager="kuberos"):
    """What the API server holds after an apply of ``config``: the stamp, the server's own fields and defaults."""
    live = stamped(config)
    live["metadata"].update(uid="u-1", resourceVersion="7", managedFields=[{"manager": manager, "operation": "Apply"}])
    live["metadata"]["annotations"]["deployment.kubernetes.io/revision"] = "1"
    container = live["spec"]["template"]["spec"]["containers"][0]
    container.update(terminationMessagePath="/dev/termination-log", imagePullPolicy="IfNotPresent")
    live["status"] = {"replicas": 1}
    return live


def test_an_object_applied_as_rendered_and_left_alone_is_unchanged():
    assert unchanged(CONFIG, live_after_apply(), "kuberos")


def test_anything_else_asks_for_a_dry_run():
    assert not unchanged(CONFIG, None, "kuberos")  # new
    changed = copy.deepcopy(CONFIG)
    changed["spec"]["template"]["spec"]["containers"][0]["image"] = "r/p:2"
    assert not unchanged(changed, live_after_apply(), "kuberos")  # a new configuration (another digest)
    assert not unchanged(CONFIG, live_after_apply(manager="someone"), "kuberos")  # the fields are another's
    edited = live_after_apply()
    edited["spec"]["template"]["spec"]["containers"][0]["image"] = "r/p:evil"  # kubectl edit
    assert not unchanged(CONFIG, edited, "kuberos")
    removed = live_after_apply()
    del removed["metadata"]["labels"]  # a field it set, gone
    assert not unchanged(CONFIG, removed, "kuberos")
    added = live_after_apply()
    added["spec"]["template"]["spec"]["containers"].append({"name": "sidecar", "image": "x"})
    assert not unchanged(CONFIG, added, "kuberos")  # a list of another length is not read item by item
    unstamped = live_after_apply()
    del unstamped["metadata"]["annotations"][APPLIED]  # applied before the digest existed
    assert not unchanged(CONFIG, unstamped, "kuberos")


def test_the_digest_leaves_out_the_stamp_and_values_keep_their_types():
    assert applied_hash(stamped(CONFIG)) == applied_hash(CONFIG) != applied_hash({**CONFIG, "kind": "ConfigMap"})
    assert not holds({"port": "80"}, {"port": 80}) and not holds({"on": 1}, {"on": True}) and holds({"a": 1, "b": 2}, {"a": 1})
