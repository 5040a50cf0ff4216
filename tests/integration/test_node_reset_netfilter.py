"""What kubeadm reset leaves and the node_reset role removes from netfilter (roles/node_reset/files/clean-netfilter.sh),
run for real in a network namespace this test creates: the chains of kube-proxy, Cilium and Calico and every rule
that jumps to them go, in every table; a site's own chains and rules stay; --check changes nothing; a second run
finds nothing. Needs root, ``ip netns`` and iptables (a failure in CI, a skip elsewhere)."""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid

import pytest
from helpers import ROOT

SCRIPT = os.path.join(ROOT, "roles", "node_reset", "files", "clean-netfilter.sh")
pytestmark = pytest.mark.host  # it makes a network namespace on this machine

PATTERNS = ["KUBE-", "CILIUM", "OLD_CILIUM", "cali-"]
SETUP = [
    "iptables -N KUBE-SERVICES", "iptables -A INPUT -j KUBE-SERVICES", "iptables -A KUBE-SERVICES -p tcp --dport 1 -j ACCEPT",
    "iptables -N cali-INPUT", "iptables -A INPUT -j cali-INPUT",
    "iptables -N SITE-FIREWALL", "iptables -A INPUT -j SITE-FIREWALL", "iptables -A SITE-FIREWALL -p tcp --dport 22 -j ACCEPT",
    "iptables -A FORWARD -p tcp --dport 8080 -j DROP",
    "iptables -t nat -N CILIUM_POST_nat", "iptables -t nat -A POSTROUTING -j CILIUM_POST_nat",
    "iptables -t nat -N OLD_CILIUM_POST_nat", "iptables -t nat -A POSTROUTING -j OLD_CILIUM_POST_nat",
    "iptables -t nat -A POSTROUTING -s 10.1.0.0/16 -j MASQUERADE",
    "ip6tables -N KUBE-FIREWALL", "ip6tables -A OUTPUT -j KUBE-FIREWALL",
]  # fmt: skip


@pytest.fixture
def namespace():
    missing = [tool for tool in ("ip", "iptables-save", "ip6tables-save") if not shutil.which(tool)]
    if os.geteuid() != 0 or missing:
        why = f"needs root and {', '.join(missing) or 'ip netns'}"
        if os.environ.get("CI"):
            pytest.fail(why)
        pytest.skip(why)
    name = f"kr-reset-{uuid.uuid4().hex[:8]}"
    subprocess.run(["ip", "netns", "add", name], check=True)
    try:
        yield name
    finally:
        subprocess.run(["ip", "netns", "delete", name], check=False)


def _in(namespace: str, command: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", "netns", "exec", namespace, "sh", "-c", command], capture_output=True, text=True,
                          timeout=60, check=False)  # fmt: skip


def _rules(namespace: str) -> str:
    return _in(namespace, "iptables-save; ip6tables-save").stdout


def _clean(namespace: str, *flags: str) -> subprocess.CompletedProcess:
    return _in(namespace, " ".join(["sh", SCRIPT, *flags, *PATTERNS]))


def test_the_clusters_chains_go_with_the_rules_that_jump_to_them_and_the_sites_stay(namespace):
    for command in SETUP:
        assert _in(namespace, command).returncode == 0, command
    before = _rules(namespace)
    checked = _clean(namespace, "--check")
    assert checked.returncode == 0 and "would change iptables" in checked.stdout, checked
    assert _rules(namespace) == before  # --check changes nothing

    done = _clean(namespace)
    assert done.returncode == 0 and "changed iptables" in done.stdout and "changed ip6tables" in done.stdout, done
    after = _rules(namespace)
    for name in ("KUBE-", "CILIUM", "cali-"):
        assert name not in after, after
    for kept in (":SITE-FIREWALL", "-A INPUT -j SITE-FIREWALL", "--dport 22 -j ACCEPT", "--dport 8080 -j DROP", "-j MASQUERADE"):
        assert kept in after, (kept, after)

    again = _clean(namespace)
    assert again.returncode == 0 and again.stdout == "", again  # nothing left to do: nothing said


def test_no_prefix_is_refused():
    done = subprocess.run(["sh", SCRIPT], capture_output=True, text=True, timeout=30, check=False)
    assert done.returncode == 2 and "no chain prefix" in done.stderr
