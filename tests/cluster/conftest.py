"""A real local control plane for the tests in this folder, started once per session with the
local_cluster playbook on ports of its own (a developer's own local cluster is left alone)."""

from __future__ import annotations

import json
import os
import re
import subprocess

import pytest
from conftest import ROOT, venv_tool

TEST_PORTS = {
    "apiserver": 26443,
    "etcd_client": 22379,
    "etcd_peer": 22380,
    "controller_manager": 26257,
    "scheduler": 26259,
    "kwok": 26247,
}


def playbook(name, *extra, timeout=1800):
    env = {**os.environ, "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1", "ANSIBLE_FORCE_COLOR": "0"}
    command = [venv_tool("ansible-playbook"), f"playbooks/{name}", "-i", "inventories/local", *[str(e) for e in extra]]
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    recap = re.search(r"localhost\s+: ok=(\d+)\s+changed=(\d+)\s+unreachable=\d+\s+failed=(\d+)", result.stdout)
    result.changed = int(recap.group(2)) if recap else None
    return result


class Cluster:
    def __init__(self, state_dir):
        self.state_dir = str(state_dir)
        self.kubeconfig = os.path.join(self.state_dir, "kubeconfig")
        self.vars = ["-e", json.dumps({"local_cluster_state_dir": self.state_dir, "local_cluster_ports": TEST_PORTS})]

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


@pytest.fixture(scope="session")
def cluster(tmp_path_factory):
    cluster = Cluster(tmp_path_factory.mktemp("cluster"))
    started = cluster.start()
    assert started.returncode == 0, started.stdout[-6000:] + started.stderr[-3000:]
    cluster.first_start = started
    yield cluster
    cluster.stop(state="absent")
