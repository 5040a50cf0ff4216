"""Fuzzing the options of two modules: ``rosdeployment_logs`` (``logs.yml``: lines, follow, container, previous, and
the deployment, module and robot named) against a fleet with a module on two robots, and ``rosdeployment_rollout``
(``rollout.yml``: canary, wave size, soak, gate and pre-pull timeouts, update-lock wait, the graph check's timeout and
window). The drawn values go through Ansible's own argument validation first (the modules' types: what ``-e
lines=abc`` becomes, or its refusal), then the modules' checks. Each case gives a result (a log read, options taken),
or one refusal that names the option or the value it could not find; a taken option is finite and bounded, so a
wave's gate or soak ends."""

from __future__ import annotations

import base64
import json
import math

import yaml
from ansible.module_utils.common.arg_spec import ArgumentSpecValidator
from fuzz_bounds import fuzz_settings, run_case
from fuzz_values import hostile_value, mostly
from hypothesis import given
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels, rollout
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import module_log_reader
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ros.graph_check import graph_check_problem
from ansible_collections.kuberos.platform.plugins.modules import rosdeployment_logs
from ansible_collections.kuberos.platform.plugins.modules.rosdeployment_rollout import ARGUMENT_SPEC as ROLLOUT_SPEC

NAMESPACE = "kuberos-test-fleet"


class OptionRefused(KuberosError):
    """Ansible's argument validation refused an option (the module never ran)."""


def validated(spec: dict, params: dict) -> dict:
    """``params`` as Ansible hands them to the module (converted to the options' types), or ``OptionRefused``."""
    result = ArgumentSpecValidator(spec).validate(params)
    if result.error_messages:  # shown as Ansible shows a failed task's msg: in JSON, control characters escaped
        raise OptionRefused("; ".join(json.dumps(m)[1:-1] for m in result.error_messages))
    return result.validated_parameters


def ansible_located(error: KuberosError, options) -> str:
    """An Ansible refusal names the argument: "argument 'lines' is of type ..."."""
    return "" if any(f"argument '{name}'" in str(error) for name in options) else "names no argument"


def _deployment(name: str, module: str, robot: str = "", robots: str = "") -> dict:
    meta = {
        "name": name,
        "namespace": NAMESPACE,
        "labels": {labels.DEPLOYMENT: "pnp", labels.MODULE: module, labels.COMPONENT: "ros-module"},
    }
    if robot:
        meta["labels"][labels.ROBOT] = robot
    if robots:
        meta["annotations"] = {labels.ROBOTS_ANNOTATION: robots}
    return {"kind": "Deployment", "metadata": meta}


DEPLOYMENTS = [
    _deployment("pnp-planner-fetch-1", "planner", "fetch-1"),
    _deployment("pnp-planner-fetch-2", "planner", "fetch-2"),
    _deployment("pnp-coordinator-shared-0", "coordinator", robots="fetch-1,fetch-2"),
]
SECRET_VALUE = "s3cr3t-value"


def _pod(instance: str) -> dict:
    return {
        "metadata": {"name": f"{instance}-abc", "namespace": NAMESPACE, "labels": {labels.INSTANCE: instance},
                     "creationTimestamp": "2026-11-28T10:00:00Z"},
        "spec": {"nodeName": "edge-1", "containers": [{"name": "main"}, {"name": "sidecar"}],
                 "volumes": [{"name": "tls", "secret": {"secretName": "api"}}]},
    }  # fmt: skip


class FakeKube:
    """The fleet's module Deployments and pods, a Secret, and a log the case draws."""

    def __init__(self, log_text: str):
        self.log_text = log_text

    def list(self, kind, namespace="", selector=""):
        if kind == "Deployment":
            return [d for d in DEPLOYMENTS if namespace in ("", NAMESPACE) and f"{labels.DEPLOYMENT}=pnp," in selector]
        instance = selector.split("=", 1)[1]
        return [_pod(d["metadata"]["name"]) for d in DEPLOYMENTS if d["metadata"]["name"] == instance]

    def get(self, kind, name, namespace=""):
        return {"metadata": {"name": name}, "data": {"token": base64.b64encode(SECRET_VALUE.encode()).decode()}}

    def log(self, pod, namespace, container="", tail_lines=None, since_seconds=None, timestamps=False, previous=False):
        return self.log_text


class Clock:
    """A clock that a sleep moves on: ``follow`` takes no wall time."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now

    def sleep(self, seconds):
        self.now += seconds


names = st.one_of(
    st.sampled_from(["pnp", "planner", "coordinator", "fetch-1", "fetch-2", "test-fleet", ""]), st.text(max_size=20)
)
stamped_lines = st.lists(
    st.tuples(
        st.sampled_from(["2026-11-28T10:00:00.5Z", "2026-11-28T10:00:01Z", "garbage", "", "9" * 400]),
        st.one_of(st.text(max_size=80), st.sampled_from([SECRET_VALUE, "x" * 20_000, "-----BEGIN RSA PRIVATE KEY-----"])),
    ).map(" ".join),
    max_size=30,
).map("\n".join)


# ansible-core's own conversion fails with a traceback (OverflowError) before the module runs on an infinity for an
# int option (check_type_int) and an integer beyond a float's range for a float option (check_type_float): ansible-
# core's, not the collection's, so such values are not drawn for those options.
for_int = hostile_value.filter(lambda value: not (isinstance(value, float) and math.isinf(value)))
for_float = hostile_value.filter(lambda value: not (isinstance(value, int) and abs(value) > 1e308))
lines_option = st.one_of(
    st.sampled_from([1, 100, 10000, 10001, 0, -1, 10**400, "100", "9" * 400, "1e3", "0x10", math.nan]),
    st.integers(),
    for_int,
)
follow_option = st.one_of(
    st.sampled_from([0.0, 1.0, 600.0, 600.5, -1.0, math.nan, math.inf, 1e308, "nan", "inf", "1e400", "5"]),
    st.floats(),
    for_float,
)
LOG_OPTIONS = ("lines", "follow", "deployment", "module", "robot", "container", "fleet", "previous")


def documented_spec(module) -> dict:
    """A module's options as Ansible validates them, from its DOCUMENTATION (ansible-test's validate-modules keeps
    that equal to its argument_spec; the doc fragments' options, such as kubeconfig, are left out)."""
    options = yaml.safe_load(module.DOCUMENTATION)["options"]
    keys = ("type", "default", "required", "elements", "choices")
    return {name: {key: option[key] for key in keys if key in option} for name, option in options.items()}


LOGS_SPEC = documented_spec(rosdeployment_logs)


def logs_located(error: KuberosError) -> str:
    if isinstance(error, OptionRefused):
        return ansible_located(error, LOG_OPTIONS)
    message = str(error)
    if message.startswith(("lines must", "follow must", *(f"{option}: " for option in LOG_OPTIONS))):
        return ""
    found = isinstance(error, module_log_reader.LogNotFound)
    if found and (message.startswith(("deployment ", "module ")) or " has no container " in message or " has no pod" in message):
        return ""
    return f"names none of the options ({', '.join(LOG_OPTIONS)}) nor what it could not find"


@fuzz_settings(500)
@given(
    deployment=mostly(st.just("pnp"), names),
    module=mostly(st.sampled_from(["planner", "coordinator"]), names),
    robot=mostly(st.sampled_from(["fetch-1", "fetch-2"]), names),
    fleet=mostly(st.sampled_from(["", "test-fleet"]), names),
    container=mostly(st.sampled_from(["", "main", "sidecar"]), names),
    lines=mostly(st.sampled_from([1, 100, 10000]), lines_option),
    follow=mostly(st.sampled_from([0.0, 2.0, 600.0]), follow_option),
    previous=mostly(st.booleans(), hostile_value),
    log_text=stamped_lines,
)
def test_reading_a_modules_log_is_lines_or_a_refusal_naming_the_option(
    deployment, module, robot, fleet, container, lines, follow, previous, log_text
):
    clock = Clock()
    case = dict(deployment=deployment, module=module, robot=robot, fleet=fleet, container=container, lines=lines,
                follow=follow, previous=previous)  # fmt: skip
    taken = {}

    def read():
        p = taken.update(validated(LOGS_SPEC, case)) or taken
        return module_log_reader.read_module_log(
            FakeKube(log_text), p["deployment"], p["module"], p["robot"], p["fleet"], p["container"], p["lines"],
            p["follow"], p["previous"], clock=clock, sleep=clock.sleep,
        )  # fmt: skip

    outcome = run_case("logs-options", read, KuberosError, logs_located, {**case, "log_text": log_text})
    if outcome.error is None:
        assert 1 <= taken["lines"] <= 10000 and 0 <= taken["follow"] <= module_log_reader.MAX_FOLLOW_S, taken
        assert not any(SECRET_VALUE in line for line in outcome.value["lines"]), outcome.value["lines"]


durations_option = st.one_of(
    st.sampled_from([0.0, 0.5, 5.0, 120.0, 600.0, 3600.0, 3600.5, 86400.0, 86401.0, -1.0, math.nan, math.inf, -math.inf]),
    st.floats(),
    st.integers(-(10**6), 10**6),
    st.sampled_from(["nan", "inf", "-inf", "1e400", "5", "10**9", "", "5s"]),
    for_float,
)
counts_option = st.one_of(st.sampled_from([0, 1, 10, 1000, 1001, -1, 10**400, "3", "9" * 400]), st.integers(), for_int)
ROLLOUT_DEFAULTS = {"canary": 1, "wave_size": 10, "soak": 5.0, "gate_timeout": 120.0, "update_lock_wait": 120.0,
                    "prestage_timeout": 600.0, "prestage_parallel": 10, "graph_check_timeout": 30.0,
                    "graph_check_window": 3.0}  # fmt: skip
COUNTS = ("canary", "wave_size", "prestage_parallel")


@st.composite
def rollout_params(draw) -> dict:
    params = dict(ROLLOUT_DEFAULTS)
    for name in draw(st.lists(st.sampled_from(sorted(params)), min_size=1, max_size=2, unique=True)):
        params[name] = draw(counts_option if name in COUNTS else durations_option)
    return params


def options_located(error: KuberosError) -> str:
    if isinstance(error, OptionRefused):
        return ansible_located(error, ROLLOUT_DEFAULTS)
    first = str(error).split(" ", 1)[0]
    return "" if first in ROLLOUT_DEFAULTS else f"does not start with an option's name ({', '.join(ROLLOUT_DEFAULTS)})"


@fuzz_settings(500)
@given(params=rollout_params())
def test_the_rollouts_options_are_taken_bounded_or_refused_naming_the_option(params):
    spec = {name: ROLLOUT_SPEC[name] for name in ROLLOUT_DEFAULTS}
    taken = {}

    def check():
        taken.update(validated(spec, params))
        why = rollout.option_problem(taken) or graph_check_problem(taken)
        if why:
            raise KuberosError(why)
        plan = rollout.plan_rollout([], [], ["fetch-1"], taken["canary"], taken["wave_size"])
        assert not plan.changed
        return taken

    outcome = run_case("rollout-options", check, KuberosError, options_located, params)
    if outcome.error is None:
        for name in ROLLOUT_DEFAULTS:
            assert math.isfinite(taken[name]), (name, taken)
        for name, (low, high) in rollout.OPTION_BOUNDS.items():
            assert low <= taken[name] <= high, (name, taken)
