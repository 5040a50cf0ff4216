"""What the fuzzing tier found, each as the smallest input that showed it: a row per finding, which failed (a
traceback) before its fix and is now a located refusal. The tier's own draws may move on; these stay."""

from __future__ import annotations

import copy
import functools
import json
import os
import subprocess
import sys

import pytest
from fuzz_bounds import run_case
from helpers import ROOT
from hostile_registry import HostileRegistry
from test_fuzz_inventory import PARTNER, SOURCE, inventory_located
from test_fuzz_options import FakeKube, logs_located
from test_fuzz_registry import MANIFEST, answer, loopback_only, registry_located

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import module_log_reader
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import registry_api as api

CHALLENGE = 'Bearer realm="{realm}",service="hostile"'
ROBOT = {"kuberos_fleet": "f", "kuberos_cpu": 4, "kuberos_memory": "8Gi"}


def _inventory(hosts=None, groups=None, **extra) -> dict:
    raw = {"hosts": {"r1": dict(ROBOT), "partner": {**PARTNER, "kuberos_fleets": ["f"]}, **(hosts or {})},
           "groups": {"robots": ["r1"], "clusters": ["partner"], **(groups or {})}, **extra}  # fmt: skip
    return copy.deepcopy(raw)


# (inventory, the refusal's problem: its path and a fragment of its reason)
INVENTORY_FINDINGS = [
    pytest.param(
        _inventory(default_latency_ms={"edge": 10**400}),
        "kuberos_default_latency_ms.edge",
        "is not valid; expected a latency",
        id="a-400-digit-default-latency-OverflowError",
    ),
    pytest.param(
        _inventory(
            hosts={
                "r1": {**ROBOT, "kuberos_link_latency_ms": {"e1": 10**400}},
                "e1": {"kuberos_cpu": 4, "kuberos_memory": "8Gi"},
            },
            groups={"edge": ["e1"]},
        ),
        "hosts.r1.kuberos_link_latency_ms.e1",
        "is not valid; expected a latency",
        id="a-400-digit-link-latency-OverflowError",
    ),
    pytest.param(
        _inventory(hosts={"r1": {**ROBOT, "kuberos_cpu": "9" * 400}}),
        "hosts.r1.kuberos_cpu",
        "is not valid; expected a CPU quantity",
        id="a-400-digit-cpu-text-OverflowError",
    ),
    pytest.param(
        _inventory(groups={"clusters": ["partner", ["x"]]}),
        "groups.clusters[1]",
        "is not valid; expected a host name",
        id="a-list-as-a-cluster-name-TypeError",
    ),
    pytest.param(
        _inventory(hosts={"partner": "x"}),
        "hosts.partner",
        "is not valid; expected a mapping of variables",
        id="a-clusters-variables-as-text-AttributeError",
    ),
]


@pytest.mark.parametrize(("raw", "path", "reason"), INVENTORY_FINDINGS)
def test_inventory_findings_are_located_refusals(raw, path, reason):
    outcome = run_case("findings", lambda: load_inventory(raw, SOURCE), SpecError, inventory_located, raw)
    assert isinstance(outcome.error, SpecError), outcome.value
    problems = [p for p in outcome.error.problems if p.path == path]
    assert problems and reason in problems[0].message, str(outcome.error)


# -- the rollout's options: a soak or gate of .inf (or NaN) was taken, and a wave would never end ------------------


def _module_message(module: str, args: dict, tmp_path) -> str:
    """The message ``module`` fails with for ``args``, run as Ansible runs it (its arguments in a file)."""
    path = tmp_path / "args.json"
    path.write_text(json.dumps({"ANSIBLE_MODULE_ARGS": args}), encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": os.path.join(ROOT, ".collections")}
    done = subprocess.run(
        [sys.executable, "-m", f"ansible_collections.kuberos.platform.plugins.modules.{module}", str(path)],
        capture_output=True, text=True, env=env, timeout=60, check=False,
    )  # fmt: skip
    return json.loads(done.stdout)["msg"]


ROLLOUT_ARGS = {"src": "spec.yml", "inventory": {}, "kubeconfig": "/nonexistent/kubeconfig"}


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        pytest.param("soak", "inf", "soak must be 0 or more and at most 3600 seconds; got inf", id="soak-inf"),
        pytest.param("gate_timeout", "nan", "gate_timeout must be above 0 and at most 3600 seconds; got nan", id="gate-nan"),
        pytest.param(
            "prestage_timeout", "1e400", "prestage_timeout must be above 0 and at most 86400 seconds; got inf", id="prestage-inf"
        ),
        pytest.param(
            "update_lock_wait", "nan", "update_lock_wait must be above 0 and at most 3600 seconds; got nan", id="lock-nan"
        ),
    ],
)
def test_the_rollouts_unbounded_options_are_refused_by_name(option, value, message, tmp_path):
    assert _module_message("rosdeployment_rollout", {**ROLLOUT_ARGS, option: value}, tmp_path) == message


# -- found in files of other items of issue 44, to be fixed there (these fail until then) -------------------------


@pytest.mark.parametrize(
    ("routes", "fragment"),
    [
        pytest.param({MANIFEST: (301, {"Location": "\x80"}, b"")}, "", id="redirect-to-non-ascii-UnicodeEncodeError"),
        pytest.param({MANIFEST: (301, {"Location": "https://a..b/"}, b"")}, "", id="redirect-to-empty-label-UnicodeError"),
        pytest.param({MANIFEST: (301, {"Location": "https://[::1/"}, b"")}, "", id="redirect-to-bad-ipv6-ValueError"),
        pytest.param(
            {MANIFEST: (401, {"WWW-Authenticate": CHALLENGE}, b""), "/token": (429, {}, b"\x00")},
            "HTTP 429",
            id="token-error-body-with-a-control-character",
        ),
    ],
)
def test_registry_findings_are_refusals_naming_the_registry(routes, fragment, tmp_path):
    with HostileRegistry(str(tmp_path)) as server, loopback_only(server.port):
        realm = server.url("127.0.0.1", "/token")
        server.routes = {
            path: answer(status, {k: v.replace("{realm}", realm) for k, v in headers.items()}, body)
            for path, (status, headers, body) in routes.items()
        }
        client = api.RegistryApi(server.address, "alice", "s3cret", server.ca_file, deadline_s=5.0)
        outcome = run_case("findings", lambda: client.manifest_digest("app", "1.0"), api.RegistryError,
                           registry_located(server.address), routes)  # fmt: skip
        assert outcome.error is not None and fragment in str(outcome.error)


@pytest.mark.parametrize("name", ["deployment", "module"])
def test_a_log_refusal_shows_a_control_character_escaped(name):
    chosen = {"deployment": "pnp", "module": "planner", name: "a\x1b[2J"}
    read = functools.partial(module_log_reader.read_module_log, FakeKube(""), chosen["deployment"], chosen["module"], "fetch-1")
    outcome = run_case("findings", read, KuberosError, logs_located, chosen)
    assert "a\\x1b[2J" in str(outcome.error), str(outcome.error)
