"""From bare machines to a running fleet: the sample site on lab machines, as an infrastructure engineer and then a
developer would run it (plugins/module_utils/kuberos_lab/site_lab.py).

Seven lab machines (Debian under systemd-nspawn, each its own network stack, systemd, containerd and cgroup
subtree, reached over SSH as a non-root user with sudo) stand for the sample inventory's hosts: three control planes
behind a keepalived virtual IP, an edge worker, two robots, and a cloud VM that reaches the site only through the
WireGuard tunnel. In order:

1. ``site.yml`` for real: every node Ready with its labels and taints, three etcd members, the virtual IP held by
   one control plane, the cloud VM's node IP its tunnel address; admin.conf 0600 here, no join token left;
2. the pod network for real (Cilium, ``kuberos_cni``, built here from its Go module): a robot's pod reaches pods on
   the edge worker and on the cloud VM (through the tunnel, a file larger than any window: the MTU holds), and a
   NetworkPolicy refuses another pod;
3. a second ``site.yml`` changes nothing;
4. ``controller.yml`` (in the cluster) and ``deploy.yml`` of ``examples/pick-and-place.yml`` (aimed at the picking
   fleet, its CPU requests divided by four for the lab's two cores: ``site_lab.lab_example``): pods Running where
   placed, onboard modules on the robots, ROS 2 between a robot, the edge and the cloud VM through the fleet's
   discovery servers: a pick cycle completes;
5. ``register_robot.yml`` with the join adds a robot, which gets its onboard module on the next deploy;
6. undeploy removes every pod of the app;
7. a robot powered off and one in the inventory that never joined: ``site.yml`` succeeds, names both once, labels
   what joined and makes no Node for the other;
8. the control plane that holds the virtual IP is powered off: the API answers through the same endpoint;
9. teardown leaves this machine as it was.

Needs root, systemd-nspawn, debootstrap, and the programs ``make test`` builds (skipped locally without them, a
failure in CI). Bounded: every playbook and wait has a timeout; about 20 minutes here.
"""

from __future__ import annotations

import json
import os

import pytest
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.kubeadm_config import INIT_TOKEN_DESCRIPTION
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import machines as lab_machines
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import site_lab
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import snapshot_host

pytestmark = pytest.mark.site

# Node names: the inventory's host names, or kuberos_node_name where the sample gives one.
ROBOT, OTHER_ROBOT = "fetch-01.robots.example.internal", "fetch-02.robots.example.internal"
EDGE_WORKER, CLOUD, CONTROL_PLANES = "edge-d", site_lab.CLOUD_VM, site_lab.CONTROL_PLANES
OTHER_ROBOT_MACHINE = "fetch-02"
GHOST_ROBOT = "fetch-09.robots.example.internal"  # in the inventory, no machine: a robot that never joined


def _missing() -> list[str]:
    problems = lab_machines.missing_requirements()
    cache = os.path.expanduser(os.environ.get("KUBEROS_CACHE_DIR") or "~/.cache/kuberos")
    built = os.listdir(os.path.join(cache, "bin")) if os.path.isdir(os.path.join(cache, "bin")) else []
    if not any(name.startswith("kubeadm-") for name in built):
        problems.append("kubeadm (make binaries WITH_KUBEADM=1 WITH_NODES=1)")
    return problems


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    problems = _missing()
    if problems:
        if os.environ.get("CI"):
            pytest.fail("the site chain needs: " + ", ".join(problems))
        pytest.skip("the site chain needs: " + ", ".join(problems))
    folder = tmp_path_factory.mktemp("site")
    spec = site_lab.lab_example(os.path.join(ROOT, "examples", "pick-and-place.yml"), str(folder / "pick-and-place.yml"))
    before = snapshot_host()
    lab = site_lab.SiteLab(str(folder / "state"), ROOT)
    chain = site_lab.SiteChain(lab, spec)
    chain.before = before
    chain.render = str(folder / "rendered")
    try:
        chain.site_vars = lab.up()
        yield chain
    finally:
        lab.down(remove=True)
        print(json.dumps(chain.figures, indent=1))


def _tail(result) -> str:
    """The failed tasks (each ``fatal:`` or ``failed:`` block, with the task it belongs to), then the end of the output."""
    lines, failures, task = result.stdout.splitlines(), [], ""
    for number, line in enumerate(lines):
        if line.startswith("TASK ["):
            task = line
        elif line.startswith(("fatal:", "failed:")):
            block = [line]
            for more in lines[number + 1 : number + 40]:
                if not more.strip() or more.startswith(("TASK [", "PLAY ", "fatal:", "failed:", "ok:", "changed:")):
                    break
                block.append(more)
            failures.append("\n".join([task, *block]))
    head = "\n\n".join(failures)[-8000:]
    return (f"failed tasks:\n{head}\n\n--- the end ---\n" if head else "") + result.stdout[-6000:] + result.stderr[-2000:]


def test_site_yml_builds_an_ha_cluster_with_the_cloud_vm_over_the_vpn(chain):
    result = chain.site()
    assert result.returncode == 0, _tail(result)
    found = site_lab.nodes(chain.kube)
    assert set(found) == {ROBOT, OTHER_ROBOT, EDGE_WORKER, CLOUD, *CONTROL_PLANES}, found
    assert all(node["ready"] for node in found.values()), found
    assert found[ROBOT]["labels"]["robot.kuberos.io/name"] == "fetch-01"
    assert "kuberos.io/robot=fetch-01:NoSchedule" in found[ROBOT]["taints"], found[ROBOT]
    assert found[CLOUD]["labels"]["kuberos.io/role"] == "cloud"
    assert found[CLOUD]["internal_ip"] == chain.lab.vpn_address(CLOUD) == "10.99.0.11", found[CLOUD]  # inside the tunnel
    assert chain.figures["cloud_node_joined_over_vpn"] and chain.figures["hosts"] == 7, chain.figures
    # the lab's pod network: Cilium as built here, an agent Ready on every node
    cni = {"name": "cilium", "version": chain.site_vars["cilium_version"], "ready_agents": 7}
    assert chain.figures["cni"] == cni, chain.figures
    assert all("node-role.kubernetes.io/control-plane" in found[cp]["labels"] for cp in CONTROL_PLANES)
    assert len(site_lab.vip_holders(chain.lab.machines, CONTROL_PLANES)) == 1
    members = site_lab.etcd_members(chain.lab.machines, "edge-a")
    assert members == sorted(CONTROL_PLANES), members
    # edge servers run modules: no taint but the node lifecycle's own (the kubeadm_init scenario's check)
    edge = (*CONTROL_PLANES, EDGE_WORKER)
    edge_taints = {n: [t for t in found[n]["taints"] if not t.startswith("node.kubernetes.io/")] for n in edge}
    assert not any(edge_taints.values()), edge_taints
    # every control plane's static pods, and kube-proxy ready on every node (the kubeadm scenarios' checks)
    parts = ("etcd", "kube-apiserver", "kube-controller-manager", "kube-scheduler")
    static = {f"{part}-{cp}" for part in parts for cp in CONTROL_PLANES}

    def running_and_proxies():
        pods = chain.core.list_namespaced_pod("kube-system").items
        running = {p.metadata.name for p in pods if p.status.phase == "Running"}
        ready = [p for p in pods if p.status.container_statuses and all(c.ready for c in p.status.container_statuses)]
        proxied = {p.spec.node_name for p in ready if p.metadata.name.startswith("kube-proxy-")}
        return static <= running and proxied == set(found) and (running, proxied)

    site_lab.wait_for("the control planes' static pods and kube-proxy ready on every node", running_and_proxies, 180)
    # the administrator's credentials readable by this machine's user only; no join token left to live out its TTL
    assert os.stat(chain.lab.kubeconfig).st_mode & 0o777 == 0o600, oct(os.stat(chain.lab.kubeconfig).st_mode)
    joins = [t for t in site_lab.bootstrap_tokens(chain.kube) if t["authenticates"]]
    assert all(t["description"] == INIT_TOKEN_DESCRIPTION and t["lifetime_s"] <= 15 * 60 for t in joins), joins


def test_pods_reach_each_other_across_nodes_and_the_vpn_and_a_policy_refuses(chain):
    results = chain.network(chain.site_vars["kuberos_lab_toolbox_image"], ROBOT, EDGE_WORKER, "edge-b", CLOUD)
    assert chain.figures["cross_node_pod_traffic"], results
    assert chain.figures["cloud_pod_traffic_over_vpn"], results
    assert chain.figures["policy_denied"], results


def test_a_second_site_yml_changes_nothing(chain):
    result = chain.second_site()
    assert result.returncode == 0, _tail(result)
    changed = {host: counts["changed"] for host, counts in result.recap.items() if counts["changed"]}
    assert not changed, changed


def test_the_controller_and_the_example_run_where_placed_and_complete_a_pick_cycle(chain):
    result = chain.app(chain.render)
    assert result.returncode == 0, _tail(result)
    with open(os.path.join(chain.render, "placement.json"), encoding="utf-8") as handle:
        placement = json.load(handle)
    wanted = {i["name"]: i["node"] for i in placement["instances"]}
    onboard = {i["name"]: i["node"] for i in placement["instances"] if i["module"] == "controller"}
    running = {
        p.metadata.labels.get("kuberos.io/instance"): p.spec.node_name
        for p in chain.core.list_pod_for_all_namespaces(label_selector="kuberos.io/instance").items
        if p.status.phase == "Running"
    }
    assert {k: running.get(k) for k in wanted} == wanted, (wanted, running)
    assert set(onboard.values()) == {ROBOT, OTHER_ROBOT}, onboard
    # every image pinned by digest through the lab's mirror (rosdeployment_pin_images), and pulled so by the nodes
    pods = chain.core.list_namespaced_pod(f"kuberos-{site_lab.FLEET}", label_selector="app.kubernetes.io/managed-by=kuberos")
    images = {c.image for p in pods.items for c in p.spec.containers}
    assert images and all("@sha256:" in image for image in images), images
    cycles = chain.pick_cycles("fetch-01", site_lab.FLEET, cycles=1)
    assert cycles["returncode"] == 0 and chain.figures["pick_cycles_completed"] >= 1, cycles["output"]


def test_the_fleets_policies_admit_its_own_pods_and_refuse_another_fleets(chain):
    """The CNI (Cilium) enforces the NetworkPolicies deploy rendered in the app's fleet namespace (the pick cycle above ran under
    them): a pod of the fleet reaches a server of the fleet; a pod of another fleet, and one of the namespace that may
    read metrics ports (on another port), do not."""
    results = chain.fleet_isolation(chain.site_vars["kuberos_lab_toolbox_image"], EDGE_WORKER)
    assert chain.figures["fleet_isolation"] == {"same-fleet": True, "other-fleet": False, "metrics-ns": False}, results
    assert results["other-fleet"]["bytes"] == 0 and results["metrics-ns"]["bytes"] == 0, results


def test_a_registered_robot_joins_and_gets_its_onboard_module(chain):
    result = chain.register_robot()
    assert result.returncode == 0, _tail(result)
    new = site_lab.NEW_ROBOT
    assert site_lab.nodes(chain.kube)[new]["ready"]
    result = chain.deploy(chain.render)
    assert result.returncode == 0, _tail(result)
    pods = chain.core.list_pod_for_all_namespaces(label_selector="kuberos.io/instance").items
    assert any(p.spec.node_name == new and p.status.phase == "Running" for p in pods), [
        (p.metadata.name, p.spec.node_name, p.status.phase) for p in pods
    ]


def test_undeploy_removes_every_pod_of_the_app(chain):
    result = chain.undeploy()
    assert result.returncode == 0, _tail(result)
    site_lab.wait_for(
        "no pod of the app", lambda: not chain.core.list_pod_for_all_namespaces(label_selector="kuberos.io/instance").items, 180
    )


def test_site_yml_leaves_a_powered_off_robot_and_one_that_never_joined_and_says_so_once(chain):
    result = chain.site_with_robots_offline(OTHER_ROBOT_MACHINE, GHOST_ROBOT, site_lab.UNUSED_ADDRESS)
    assert result.returncode == 0, _tail(result)
    assert len(result.said) == 1 and OTHER_ROBOT in result.said[0] and GHOST_ROBOT in result.said[0], result.said
    assert site_lab.NEW_ROBOT not in result.said[0], result.said  # the registered robot is on: reached and finished
    found = site_lab.nodes(chain.kube)
    assert GHOST_ROBOT not in found and OTHER_ROBOT in found, sorted(found)  # no Node without a kubelet behind it
    assert chain.figures["site_run_with_robot_offline_ok"], chain.figures


def test_the_api_answers_through_the_virtual_ip_after_losing_its_control_plane(chain):
    holder = chain.lose_vip_holder()
    assert site_lab.vip_holders(chain.lab.machines, [cp for cp in CONTROL_PLANES if cp != holder]), holder


def test_teardown_leaves_the_host_as_it_was(chain):
    chain.lab.down(remove=True)
    after = snapshot_host()
    changed = {key: (chain.before[key], after[key]) for key in chain.before if chain.before[key] != after[key]}
    assert not changed, changed
