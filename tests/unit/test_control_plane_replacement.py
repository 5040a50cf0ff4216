"""Replacing a lost control plane (issue: the first control plane was special): kubeadm init only for a new
cluster, every control plane joins an existing one (the first too), the rebuilt one's stale etcd member found, the
tokens issued by a control plane that serves, and VRRP authenticated."""

from __future__ import annotations

import os

import pytest
import yaml
from helpers import ROOT
from test_kubeadm_config import HA, render

from ansible_collections.kuberos.platform.plugins.filter.etcd_stale_members import etcd_stale_members
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.control_planes import stale_members

MEMBERS = [
    {"ID": "1111", "name": "edge-1", "peerURLs": ["https://10.0.0.11:2380"], "clientURLs": ["https://10.0.0.11:2379"]},
    {"ID": "2222", "name": "edge-2", "peerURLs": ["https://10.0.0.12:2380"]},
    {"ID": "3333", "name": "", "peerURLs": ["https://10.0.0.13:2380"]},  # added, never started
]


@pytest.mark.parametrize(
    ("init_host", "actions"),
    [
        (None, ["init", "join-control-plane", "join-control-plane"]),  # a new cluster: the first control plane inits
        ("", ["join-control-plane"] * 3),  # the cluster exists: every control plane joins it, the first one too
        ("edge-2", ["join-control-plane", "init", "join-control-plane"]),  # the init configuration of one that serves
    ],
)
def test_only_a_new_cluster_is_initialised(init_host, actions):
    options = {} if init_host is None else {"init_host": init_host}
    assert [render(host, HA, **options)["action"] for host in HA] == actions
    assert render("fetch-1", HA, **options)["action"] == "join-worker"


def test_a_rebuilt_control_planes_member_is_found_by_name_or_by_its_peer_address():
    assert [m["ID"] for m in stale_members(MEMBERS, ["edge-1"], ["https://10.0.0.11:2380"])] == ["1111"]
    assert [m["ID"] for m in stale_members(MEMBERS, ["edge-c"], ["https://10.0.0.13:2380"])] == ["3333"]
    assert stale_members(MEMBERS, ["edge-9"], ["https://10.0.0.99:2380"]) == []  # a new control plane: nothing to remove
    assert stale_members([{"name": "edge-1"}, "junk", None], ["edge-1"], []) == []  # not a member: left alone
    found = etcd_stale_members(MEMBERS, ["edge-1", "edge-2"], ["https://10.0.0.12:2380"])
    assert found == [{"ID": "1111", "name": "edge-1", "peerURLs": ["https://10.0.0.11:2380"]},
                     {"ID": "2222", "name": "edge-2", "peerURLs": ["https://10.0.0.12:2380"]}]  # fmt: skip


def _role_tasks(role: str) -> list[dict]:
    with open(os.path.join(ROOT, "roles", role, "tasks", "main.yml"), encoding="utf-8") as handle:
        return yaml.safe_load(handle)


def _walk(tasks):
    for task in tasks:
        yield task
        yield from _walk(task.get("block") or [])
        yield from _walk(task.get("rescue") or [])
        yield from _walk(task.get("always") or [])


def test_tokens_and_certificates_come_from_a_control_plane_that_serves_never_the_first_by_rule():
    for role in ("kubeadm_init", "kubeadm_join"):
        delegated = {t["name"]: t.get("delegate_to") for t in _walk(_role_tasks(role)) if "delegate_to" in t}
        assert delegated and all("token_host" in where for where in delegated.values()), (role, delegated)
    with open(os.path.join(ROOT, "playbooks", "site.yml"), encoding="utf-8") as handle:
        plays = yaml.safe_load(handle)
    fetch = next(p for p in plays if "kubeconfig" in p["name"] and "Fetch" in p["name"])
    assert fetch["hosts"] == "kuberos_token_host"


def test_vrrp_adverts_carry_the_control_planes_password():
    with open(os.path.join(ROOT, "roles", "control_plane_vip", "templates", "keepalived.conf.j2"), encoding="utf-8") as f:
        template = f.read()
    assert "auth_type PASS" in template and "auth_pass {{ control_plane_vip__auth_pass }}" in template
    secret = next(t for t in _walk(_role_tasks("control_plane_vip")) if t["name"].startswith("Keep the VRRP password"))
    assert secret["ansible.builtin.copy"]["mode"] == "0600" and secret["no_log"] is True
