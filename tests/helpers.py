"""Helpers shared by the test suites: paths, the embedded inventory, running playbooks, a test cluster."""

from __future__ import annotations

import contextlib
import functools
import glob
import json
import os
import re
import subprocess
import sys
import textwrap

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
VENV_BIN = os.path.join(ROOT, ".venv", "bin")


def yml(text: str) -> str:
    """Dedented YAML whose first line is line 1."""
    return textwrap.dedent(text).lstrip("\n")


def without_module(text: str, name: str) -> str:
    """A spec's text (examples/pick-and-place.yml's layout) without the module ``name`` and without the modules'
    declared topics: with a module gone, the others' subscriptions of its topics would be refused (kuberos.topics)."""
    start = text.index(f"- name: {name}\n")
    following = text.find("\n- name: ", start + 1)
    text = text[:start] + (text[following + 1 :] if following != -1 else "")
    return re.sub(r"^  topics:\n(?:    .*\n)*", "", text, flags=re.M)


# The smallest valid spec, lines 1-7: a module's extra lines start at line 8, metadata's at line 4.
SPEC_BASE = yml(
    """
    metadata:
      name: demo
      targetFleet: test-fleet
    rosModules:
    - name: planner
      image: registry/planner:1.0
      launch: ros2 launch planner planner.launch.py
    """
)
# A catalog of two modules, lines 1-13: fields added to the planner's version 1.0.0 start at line 14.
CATALOG_BASE = yml(
    """
    apiVersion: kuberos.io/v1alpha1
    kind: RosModuleCatalog
    modules:
    - name: perception
      versions:
      - version: 0.1.0
        image: registry/perception:0.1
        launch: [ros2 run perception node]
    - name: planner
      versions:
      - version: 1.0.0
        image: registry/planner:1.0
        launch: ros2 launch planner planner.launch.py
    """
)


def wireguard_private_keys(root_pattern: str) -> list[str]:
    """The WireGuard private keys under every root filesystem matching ``root_pattern`` (a glob): what the wireguard
    role wrote to ``etc/wireguard/*.key``, to check none appears in an output."""
    found = []
    for path in sorted(glob.glob(os.path.join(root_pattern, "etc", "wireguard", "*.key"))):
        with open(path, encoding="utf-8") as handle:
            found.append(handle.read().strip())
    return found


def venv_tool(name: str) -> str:
    path = os.path.join(VENV_BIN, name)
    return path if os.path.exists(path) else os.path.join(os.path.dirname(sys.executable), name)


@functools.cache
def inventory_raw(path: str = "inventories/local") -> dict:
    """Read an inventory with Ansible's own inventory command, then the core (as the simulator does)."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.ansible_inventory import read_inventory

    raw = read_inventory(os.path.join(ROOT, path))
    load_inventory(raw, source=path)
    return raw


def playbook(name, *extra, inventory="inventories/local", timeout=1800):
    """Run playbooks/<name> from the checkout; the result carries ``changed`` from the recap."""
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1", "ANSIBLE_FORCE_COLOR": "0"}
    command = [venv_tool("ansible-playbook"), f"playbooks/{name}", "-i", str(inventory), *[str(e) for e in extra]]
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    recap = re.search(r"localhost\s+: ok=(\d+)\s+changed=(\d+)\s+unreachable=\d+\s+failed=(\d+)", result.stdout)
    result.changed = int(recap.group(2)) if recap else None
    return result


def built_program(build: str, name: str, env: dict | None = None) -> str:
    """The program ``name`` of the cache, as ``build --print-paths`` names it; CI builds it (make test), so there a
    missing one fails the test, elsewhere it skips, naming the script that builds it."""
    import pytest

    result = subprocess.run([build, "--print-paths"], env=env, capture_output=True, text=True, timeout=60)
    paths = dict(line.split("=", 1) for line in result.stdout.splitlines() if "=" in line)
    path = paths.get(name, "")
    if not path or not os.access(path, os.X_OK):
        message = f"{name} is not built ({path or result.stderr.strip() or 'no path printed'}): run {build} (make test does)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


def built_kubeadm() -> str:
    """The kubeadm program of the cache (build-binaries.sh)."""
    build = os.path.join(ROOT, "roles", "local_cluster", "files", "build-binaries.sh")
    return built_program(build, "kubeadm", {**os.environ, "SKIP_KUBECTL": "1"})


# The Calico release whose published manifest the Go module proxy serves (scripts/calico-manifest.sh).
CALICO_RELEASE = "v3.28.5"


def calico_published_manifest() -> str:
    """Calico's published calico-vxlan.yaml, from its Go module (scripts/calico-manifest.sh, which make test runs): a
    failure in CI, elsewhere a skip without Go or a network."""
    import pytest

    done = subprocess.run([os.path.join(ROOT, "scripts", "calico-manifest.sh")], capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        if os.environ.get("CI"):
            pytest.fail("scripts/calico-manifest.sh: " + done.stderr[-2000:])
        pytest.skip("Calico's published manifest is not available here: " + done.stderr[-500:])
    return done.stdout.strip()


# KUBEROS_TEST_PORT_SHIFT moves every test port by one number, so that a second cluster test session
# (another checkout, a developer's second terminal) can run beside the first on its own ports. Pick a shift that
# keeps clear of the other session's ports: kwok sits 10 below the controller-manager and the scheduler 2 above it,
# so shifts of 2, 10 and 12 between two sessions collide (3, 37 or 100 do not).
# Each pytest-xdist worker (make test's two lanes) gets ports of its own too: 100 apart (gw0, gw1, ...).
WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0)
PORT_SHIFT = int(os.environ.get("KUBEROS_TEST_PORT_SHIFT", "0")) + 100 * WORKER


def _shifted(ports: dict) -> dict:
    return {name: port + PORT_SHIFT for name, port in ports.items()}


TEST_PORTS = {
    "apiserver": 26443,
    "etcd_client": 22379,
    "etcd_peer": 22380,
    "controller_manager": 26257,
    "scheduler": 26259,
    "kwok": 26247,
}
TEST_PORTS = _shifted(TEST_PORTS)
# A second control plane, standing for a third-party cluster.
PARTNER_PORTS = {
    "apiserver": 27443,
    "etcd_client": 23379,
    "etcd_peer": 23380,
    "controller_manager": 27257,
    "scheduler": 27259,
    "kwok": 27247,
}
PARTNER_PORTS = _shifted(PARTNER_PORTS)


def free_ports(count: int = 1) -> int:
    """The first of ``count`` consecutive TCP ports free on 127.0.0.1 now (a controller's replicas serve their
    dashboards on consecutive ports)."""
    import socket

    for _ in range(50):
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            first = probe.getsockname()[1]
        if first + count > 65535:
            continue
        taken = []
        try:
            for port in range(first, first + count):
                held = socket.socket()
                taken.append(held)
                held.bind(("127.0.0.1", port))
            return first
        except OSError:
            continue
        finally:
            for held in taken:
                held.close()
    raise RuntimeError(f"no {count} consecutive free ports on 127.0.0.1")


class Cluster:
    """The local control plane on test ports, driven through the playbooks as a user would."""

    def __init__(self, state_dir, ports=None):
        self.state_dir = str(state_dir)
        self.kubeconfig = os.path.join(self.state_dir, "kubeconfig")
        self.vars = ["-e", json.dumps({"local_cluster_state_dir": self.state_dir, "local_cluster_ports": ports or TEST_PORTS})]

    def start(self):
        return playbook("local_cluster.yml", *self.vars)

    def stop(self, state="stopped"):
        return playbook("local_cluster.yml", *self.vars, "-e", f"local_cluster_state={state}")

    def deploy(self, spec, render_dir, *extra):
        return playbook(
            "deploy.yml", "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_render_dir={render_dir}",
            "-e", f"kuberos_kubeconfig={self.kubeconfig}", *extra, timeout=600,
        )  # fmt: skip

    def undeploy(self, spec, *extra):
        return playbook("undeploy.yml", "-e", f"rosdeployment_file={spec}", "-e", f"kuberos_kubeconfig={self.kubeconfig}", *extra)

    def clients(self):
        from kubernetes import client, config

        api = config.new_client_from_config(config_file=self.kubeconfig)
        return client.CoreV1Api(api), client.AppsV1Api(api), client.DiscoveryV1Api(api)


def partner_site(core, folder, name: str, api_server: str, ca_cert: str, endpoint: str, latency_ms: float = 30) -> dict:
    """An inventory registering a third-party cluster as ``name`` (group ``clusters``, docs/inventory.md): a
    ServiceAccount with a token in that cluster (``core``: its CoreV1Api), the token encrypted with ansible-vault.
    ``endpoint`` is where that cluster's bridge clients reach this cluster's nodes. Returns the inventory's path, the
    vault password file and the token."""
    import yaml
    from kubernetes import client

    rbac = client.RbacAuthorizationV1Api(core.api_client)
    core.create_namespace({"metadata": {"name": "kuberos-partner-access"}})
    core.create_namespaced_service_account("kuberos-partner-access", {"metadata": {"name": "kuberos"}})
    rbac.create_cluster_role_binding(
        {
            "metadata": {"name": "kuberos-partner-access"},
            "roleRef": {"apiGroup": "rbac.authorization.k8s.io", "kind": "ClusterRole", "name": "cluster-admin"},
            "subjects": [{"kind": "ServiceAccount", "name": "kuberos", "namespace": "kuberos-partner-access"}],
        }
    )
    token = core.create_namespaced_service_account_token(
        "kuberos", "kuberos-partner-access", {"spec": {"expirationSeconds": 3600}}
    ).status.token
    folder = str(folder)
    password = os.path.join(folder, "vault-password")
    with open(password, "w", encoding="utf-8") as handle:
        handle.write("kuberos-test-vault\n")
    encrypted = subprocess.run(
        [venv_tool("ansible-vault"), "encrypt_string", "--vault-password-file", password, token, "--name", "kuberos_token"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    host = {
        "kuberos_latency_ms": latency_ms,
        "kuberos_fleets": ["test-fleet"],
        "kuberos_bridge_endpoint": endpoint,
        "kuberos_api_server": api_server,
        "kuberos_ca_cert": ca_cert,
        "ansible_connection": "local",
    }
    os.makedirs(os.path.join(folder, "host_vars"), exist_ok=True)
    with open(os.path.join(folder, "host_vars", f"{name}.yml"), "w", encoding="utf-8") as handle:
        handle.write(yaml.safe_dump(host) + encrypted)
    inventory = os.path.join(folder, "clusters.yml")
    with open(inventory, "w", encoding="utf-8") as handle:
        handle.write(yaml.safe_dump({"clusters": {"hosts": {name: None}}}))
    return {"inventory": inventory, "password": password, "token": token}


@contextlib.contextmanager
def deployments_denied(api_client, name: str, expression: str, message: str):
    """A ValidatingAdmissionPolicy (and its binding) that refuses Deployments failing the CEL ``expression`` with
    ``message``, for the time of the block. The API server takes a moment to enforce it: retry what it must refuse."""
    from kubernetes import client

    admission = client.AdmissionregistrationV1Api(api_client)
    rules = [{"apiGroups": ["apps"], "apiVersions": ["v1"], "operations": ["CREATE", "UPDATE"], "resources": ["deployments"]}]
    admission.create_validating_admission_policy(
        {
            "apiVersion": "admissionregistration.k8s.io/v1",
            "kind": "ValidatingAdmissionPolicy",
            "metadata": {"name": name},
            "spec": {
                "failurePolicy": "Fail",
                "matchConstraints": {"resourceRules": rules},
                "validations": [{"expression": expression, "message": message}],
            },
        }
    )
    admission.create_validating_admission_policy_binding(
        {
            "apiVersion": "admissionregistration.k8s.io/v1",
            "kind": "ValidatingAdmissionPolicyBinding",
            "metadata": {"name": name},
            "spec": {"policyName": name, "validationActions": ["Deny"]},
        }
    )
    try:
        yield
    finally:
        admission.delete_validating_admission_policy_binding(name)
        admission.delete_validating_admission_policy(name)


class MotoServer:
    """moto's server mode (PyPI ``moto``): the real EC2 query API on 127.0.0.1, refusing unknown images and instance
    types as AWS does. Started by the cloud tests; ``amazon.aws`` reaches it through ``endpoint_url``."""

    REGION = "eu-central-1"

    def __init__(self, log_path, port=None):
        self.port = port or free_ports()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = str(log_path)
        self.process = None

    def start(self, timeout=60):
        import time
        import urllib.request

        env = {**os.environ, "MOTO_ENABLE_AMI_VALIDATION": "1", "MOTO_EC2_ENABLE_INSTANCE_TYPE_VALIDATION": "1"}
        with open(self.log_path, "ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(self.port)],
                stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True,
            )  # fmt: skip
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                break
            try:
                with urllib.request.urlopen(f"{self.url}/moto-api/", timeout=2) as answer:
                    if answer.status == 200:
                        return self
            except OSError:
                time.sleep(0.2)
        self.stop()
        with open(self.log_path, encoding="utf-8", errors="replace") as log:
            raise RuntimeError(f"moto's server did not answer on {self.url} within {timeout} s:\n{log.read()[-3000:]}")

    def reset(self):
        """Forget every instance (the state of a fresh emulator)."""
        import urllib.request

        urllib.request.urlopen(urllib.request.Request(f"{self.url}/moto-api/reset", method="POST"), timeout=10).close()

    def stop(self):
        if self.process and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)

    def ec2(self):
        """A boto3 EC2 client of the emulator, with the dummy credentials moto accepts."""
        import boto3

        return boto3.client(
            "ec2", endpoint_url=self.url, region_name=self.REGION, aws_access_key_id="testing", aws_secret_access_key="testing"
        )


def remove_objects(dyn, core, objects: list[dict], selector: str, namespace: str = "kube-system") -> None:
    """Delete ``objects`` newest first (those already gone are no matter), then wait up to two minutes until no pod of
    ``selector`` is left in ``namespace`` (and delete what is)."""
    import time

    from kubernetes.dynamic.exceptions import NotFoundError, ResourceNotFoundError

    for obj in reversed(objects):
        try:
            resource = dyn.resources.get(api_version=obj["apiVersion"], kind=obj["kind"])
            resource.delete(name=obj["metadata"]["name"], namespace=obj["metadata"].get("namespace"))
        except (NotFoundError, ResourceNotFoundError):
            pass
    deadline = time.monotonic() + 120
    while core.list_namespaced_pod(namespace, label_selector=selector).items and time.monotonic() < deadline:
        time.sleep(1)
    for pod in core.list_namespaced_pod(namespace, label_selector=selector).items:
        core.delete_namespaced_pod(pod.metadata.name, namespace, grace_period_seconds=0)
