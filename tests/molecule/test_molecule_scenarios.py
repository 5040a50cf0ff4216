"""Every molecule scenario under molecule/, run as a role developer runs it: ``molecule test -s NAME``.

Each scenario makes its hosts as network namespaces running a real sshd (tests/sshlab.py, through
molecule/shared/create.yml), converges its role, converges again and requires no change (idempotence),
asserts real outcomes in its verify.yml, and removes the hosts. The hosts are kept until this test has also
read the secrets the role made on them (private keys), to check none of them appears in the output.
Needs root and Debian's openssh-server (skipped locally without them, a failure in CI).

The scenarios on lab machines (``kubeadm_init``, ``kubeadm_join``, ``cilium``) run the roles that the site chain
(tests/site) runs on seven machines, and check what it checks there too: etcd's members, every node Ready, labels and
taints, kube-proxy, pod traffic across nodes, a NetworkPolicy refusing, a second run changing nothing. They take about
12 minutes of a two-core machine, so ``make test`` checks only their playbooks' syntax (``molecule syntax``) and
``make molecule`` (``KUBEROS_MACHINE_SCENARIOS=1``) runs them whole: the loop of someone working on one of those roles.
``make test`` checks only the syntax of ``node_prereqs`` and ``wireguard`` too (about 5 minutes whole; marked ``full``:
``make test-full`` runs them): the site chain runs both roles on every machine, its
cloud VM's pods reach the site through the tunnel, its second ``site.yml`` changes nothing, and it checks that no
WireGuard private key appears in ``site.yml``'s output.
"""

from __future__ import annotations

import json
import os
import re
import subprocess

import pytest
from helpers import ROOT, VENV_BIN, wireguard_private_keys
from sshlab import missing_requirements

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import machines
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import snapshot_changes, snapshot_host

pytestmark = pytest.mark.molecule

SCENARIOS = sorted(
    name
    for name in os.listdir(os.path.join(ROOT, "molecule"))
    if os.path.isfile(os.path.join(ROOT, "molecule", name, "molecule.yml"))
)


def molecule(*args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "PATH": f"{VENV_BIN}:{os.environ.get('PATH', '')}",
        "ANSIBLE_NOCOLOR": "1",
        "NO_COLOR": "1",
        "PY_COLORS": "0",
    }
    env.pop("ANSIBLE_CONFIG", None)  # molecule writes its own
    return subprocess.run(
        [os.path.join(VENV_BIN, "molecule"), *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
    )


def lab_secrets(scenario: str) -> list[str]:
    """The private keys the scenario's roles generated on its hosts (WireGuard keys)."""
    return wireguard_private_keys(os.path.expanduser(f"~/.ansible/tmp/molecule.*.{scenario}/lab/hosts/*"))


def uses_machines(scenario: str) -> bool:
    """Scenarios on lab machines (systemd-nspawn) rather than SSH hosts in network namespaces."""
    with open(os.path.join(ROOT, "molecule", scenario, "molecule.yml"), encoding="utf-8") as handle:
        return "machines-create.yml" in handle.read()


MACHINE_SCENARIOS_ENV = "KUBEROS_MACHINE_SCENARIOS"


# Scenarios on SSH hosts whose roles the site chain also runs on its seven machines, with the same outcomes checked
# there (containerd and the kubelets' settings working on every node, pods across the tunnel, a second run changing
# nothing, no WireGuard private key in the output): run whole they are marked full (make test-full), and make test
# checks their syntax.
CHAIN_COVERED = ("node_prereqs", "wireguard")


def run_whole(scenario: str) -> bool:
    """``molecule test`` for the scenarios on SSH hosts always; on lab machines only with KUBEROS_MACHINE_SCENARIOS=1."""
    return not uses_machines(scenario) or os.environ.get(MACHINE_SCENARIOS_ENV) == "1"


def test_there_are_scenarios():
    assert {"wireguard", "node_prereqs", "robot_register", "kubeadm_init", "kubeadm_join", "cilium"} <= set(SCENARIOS)
    assert all(uses_machines(name) for name in ("kubeadm_init", "kubeadm_join", "cilium")) and not uses_machines("wireguard")


@pytest.mark.parametrize("scenario", [name for name in SCENARIOS if not run_whole(name) or name in CHAIN_COVERED])
def test_scenario_syntax(scenario):
    """A scenario not run whole here still parses: its converge playbook, its roles and their variables' names."""
    done = molecule("syntax", "-s", scenario, timeout=300)
    output = done.stdout + done.stderr
    assert done.returncode == 0, f"molecule syntax -s {scenario} exited {done.returncode}:\n{output[-6000:]}"
    assert re.search(rf"{scenario} (➜|>) syntax: Executed: Successful", output), output[-3000:]


@pytest.mark.parametrize(
    "scenario", [pytest.param(n, marks=pytest.mark.full) if n in CHAIN_COVERED else n for n in SCENARIOS if run_whole(n)]
)
def test_scenario(scenario):
    problems = machines.missing_requirements() if uses_machines(scenario) else missing_requirements()
    if problems:
        if os.environ.get("CI"):
            pytest.fail("molecule scenarios need SSH lab hosts in CI; missing: " + ", ".join(problems))
        pytest.skip("molecule scenarios need: " + ", ".join(problems))
    before = snapshot_host() if uses_machines(scenario) else None
    try:
        done = molecule("test", "-s", scenario, "--destroy", "never")
        output = done.stdout + done.stderr
        assert done.returncode == 0, f"molecule test -s {scenario} exited {done.returncode}:\n{output[-6000:]}"
        for step in ("idempotence", "verify"):  # molecule writes "➜" on a terminal, ">" otherwise
            assert re.search(rf"{scenario} (➜|>) {step}: Executed: Successful", output), output[-3000:]
        for secret in lab_secrets(scenario):
            assert secret not in output, f"a private key made by scenario {scenario} appears in molecule's output"
    finally:
        molecule("destroy", "-s", scenario, timeout=300)
    if before is not None:  # the machines' teardown leaves the host as it was: mounts, cgroups, links, sysctls, ...
        after = snapshot_host()
        assert after == before, json.dumps(snapshot_changes(before, after), indent=1)[:6000]
