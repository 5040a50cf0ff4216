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
5. ``upgrade.yml`` from the older release the site was built at (``KUBEROS_SITE_KUBERNETES_VERSION``, set by
   ``make test``) to the pinned one, with pick cycles going on: every kubelet at the new version, the API answering
   through the virtual IP (one holder), the placed modules running on, nothing on a robot restarted; every control
   plane's certificates renewed by kubeadm on the way, the renewed admin.conf here 0600. Marked ``upgrade``: ``make
   site-upgrade`` runs the chain with it; ``make test`` leaves it out (docs/testing.md: CI's time cannot hold it yet);
6. ``register_robot.yml`` with the join adds a robot, which gets its onboard module on the next deploy;
7. ``remove_node.yml`` removes that robot (its onboard module stopped by its deployment's pass): its Node gone, its
   machine reset (no kubelet, no kubeadm or CNI files, no interfaces or chains of the pod network), the other robots'
   modules untouched, the inventory forgets it as the run's last message asks; the edge worker's removal is refused
   while the app's modules there have no room elsewhere (the pass says why), and it stays schedulable;
8. ``etcd_backup.yml`` (a 0600 snapshot here), the app's deployment record deleted, ``etcd_restore.yml`` refused
   without its confirmation and run with it: the record back, the nodes Ready, the app Ready;
8b. ``certificates.yml -e renew=true``: every control plane's API server certificate ends later, one control plane at a
   time, the API through the virtual IP answering throughout (marked ``full``: ``make test-full``);
9. undeploy removes every pod of the app; then the edge worker is removed cleanly;
10. the control plane that holds the virtual IP (the first) is powered off: the API answers through the same endpoint;
11. that control plane rebuilt from a bare disk (the VPN's hub too), a robot powered off and one in the inventory that
    never joined, then one ``site.yml``: the rebuilt host joins the running cluster (no second ``kubeadm init``: its
    stale etcd member removed, tokens from a control plane that serves), three healthy etcd members, the cloud VM back
    through the rebuilt hub, never two holders of the virtual IP; the run succeeds, names both robots once, labels
    what joined and makes no Node for the robot that never joined (nor for the removed hosts);
12. ``reset.yml`` takes the site apart: every machine that answers is clean, the one powered off is named (marked
    ``full``: ``make test-full``; ``remove_node.yml`` resets two machines with the same role in step 7 and 9);
13. teardown leaves this machine as it was.

Needs root, systemd-nspawn, debootstrap, and the programs ``make test`` builds (skipped locally without them, a
failure in CI). Bounded: every playbook and wait has a timeout; about 25 minutes here, 40 to 50 with the upgrade
(14 to 20 of them).
"""

from __future__ import annotations

import json
import os

import pytest
from helpers import ROOT, wireguard_private_keys

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import record_name
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.kubeadm_config import INIT_TOKEN_DESCRIPTION
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import (
    kubeadm_images,
    site_lab,
    site_operations,
    site_removal,
    site_replace,
    site_upgrade,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import machines as lab_machines
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import snapshot_changes, snapshot_host

pytestmark = pytest.mark.site

# Node names: the inventory's host names, or kuberos_node_name where the sample gives one.
ROBOT, OTHER_ROBOT = "fetch-01.robots.example.internal", "fetch-02.robots.example.internal"
EDGE_WORKER, CLOUD, CONTROL_PLANES = "edge-d", site_lab.CLOUD_VM, site_lab.CONTROL_PLANES
EDGE_WORKER_HOST = site_removal.inventory_name(EDGE_WORKER)
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
    # the VPN's private keys stay on their hosts: none appears in site.yml's output (molecule/wireguard's check, here)
    secrets = wireguard_private_keys(chain.lab.machines.rootfs("*"))
    assert len(secrets) >= 2 and all(s and s not in result.stdout + result.stderr for s in secrets), len(secrets)


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


def _client_certificate_not_after(kubeconfig: str):
    import base64

    import yaml
    from cryptography import x509

    with open(kubeconfig, encoding="utf-8") as handle:
        user = yaml.safe_load(handle)["users"][0]["user"]
    return x509.load_pem_x509_certificate(base64.b64decode(user["client-certificate-data"])).not_valid_after_utc


@pytest.mark.upgrade
def test_kubernetes_is_upgraded_one_minor_version_with_the_app_running(chain):
    """upgrade.yml from the older release the site was built at (KUBEROS_SITE_KUBERNETES_VERSION, which make test sets)
    to the pinned one, with the app running and pick cycles going on: every kubelet and the cluster's configuration at
    the new version, the API answering through the virtual IP, one holder of it, the placed modules running on (a
    drain leaves them: bound to their nodes), nothing on a robot restarted. Then check mode: nothing left to do."""
    older = site_lab.site_kubernetes_version()
    if not older:
        message = f"the upgrade needs the site built at an older release: {site_lab.KUBERNETES_VERSION_ENV} (make test sets it)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    target = kubeadm_images.pinned_versions()["kubernetes"]
    certificates = {cp: site_operations.apiserver_not_after(chain.lab.machines, cp) for cp in CONTROL_PLANES}
    admin_before = _client_certificate_not_after(chain.lab.kubeconfig)
    done = site_upgrade.upgrade_site(chain, target, chain.site_vars["kuberos_lab_upgrade_binaries"], "fetch-01", site_lab.FLEET)
    assert done["result"].returncode == 0, _tail(done["result"])
    figures = {k: chain.figures[k] for k in site_upgrade.FIGURES}
    assert figures["upgrade_from"] == [older] and set(done["after"].values()) == {target}, (figures, done["after"])
    assert site_upgrade.cluster_version(chain.kube) == target
    assert figures["api_unavailable_max_s"] <= 5 and figures["api_samples_during_upgrade"] >= 60, figures
    assert figures["vip_holders_max_during_upgrade"] == 1, figures
    assert figures["onboard_pods_restarted_by_upgrade"] == 0, (figures, done["restarted"])
    assert figures["app_downtime_max_s"] <= 10, (figures, done["app_down"])
    assert figures["pick_cycles_during_upgrade"] >= 1, (figures, done["cycles"].outputs[-2:])
    # kubeadm upgrade renewed every control plane's certificates, one control plane at a time (the API answering
    # throughout, above), and the renewed admin.conf is here, 0600 (certificates.yml's renewal alone: tests/cluster)
    renewed = {cp: site_operations.apiserver_not_after(chain.lab.machines, cp) for cp in CONTROL_PLANES}
    assert all(renewed[cp] > certificates[cp] for cp in CONTROL_PLANES), (certificates, renewed)
    assert os.stat(chain.lab.kubeconfig).st_mode & 0o777 == 0o600
    assert _client_certificate_not_after(chain.lab.kubeconfig) > admin_before
    checked = chain._play("upgrade.yml", "--check")
    assert checked.returncode == 0 and "nothing to do" in " ".join(checked.stdout.split()), _tail(checked)


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


def _app_pods(chain) -> dict[str, tuple[str, str, bool]]:
    """Every pod of the app: name -> (uid, node, Ready)."""
    found = {}
    for pod in chain.core.list_pod_for_all_namespaces(label_selector="kuberos.io/instance").items:
        statuses = pod.status.container_statuses or []
        ready = pod.status.phase == "Running" and bool(statuses) and all(c.ready for c in statuses)
        found[pod.metadata.name] = (pod.metadata.uid, pod.spec.node_name, ready)
    return found


def test_a_robot_is_removed_cleanly_and_an_edge_worker_whose_modules_have_no_room_elsewhere_stays(chain):
    before = _app_pods(chain)
    assert any(node == site_lab.NEW_ROBOT for _uid, node, _ready in before.values()), before
    done = site_removal.remove_node(chain, site_lab.NEW_ROBOT, site_lab.NEW_ROBOT)
    assert done["result"].returncode == 0, _tail(done["result"])
    assert not done["node_left"] and not done["leftovers"], (site_lab.NEW_ROBOT, done["leftovers"])
    assert "Delete it from the inventory now" in done["said"] and "registered_robots.yml" in done["said"], done["said"]
    assert done["forgotten"], done

    def settled():
        pods = _app_pods(chain)
        return (pods and all(ready for _uid, _node, ready in pods.values())
                and not any(node == site_lab.NEW_ROBOT for _uid, node, _ready in pods.values()) and pods)  # fmt: skip

    after = site_lab.wait_for("the app Ready with nothing on the removed robot", settled, 300)
    # what ran for the other robots on their own computers did not move nor restart
    onboard = {name: uid for name, (uid, node, _ready) in before.items() if node in (ROBOT, OTHER_ROBOT)}
    assert onboard and {name: after.get(name, ("gone",))[0] for name in onboard} == onboard, (onboard, after)

    # The edge worker runs modules the control planes have no room for: its removal is refused before the drain,
    # and it stays schedulable with its pods untouched.
    refused = chain._play("remove_node.yml", "-e", f"node={EDGE_WORKER_HOST}", "-e", "rosdeployment_graph_check=false")
    assert refused.returncode != 0 and "is not removed" in refused.stdout and "no feasible node" in refused.stdout, _tail(refused)
    node = chain.core.read_node(EDGE_WORKER)
    assert not node.spec.unschedulable, node.spec
    on_edge = {name: uid for name, (uid, where, _ready) in after.items() if where == EDGE_WORKER}
    now = _app_pods(chain)
    assert on_edge and {name: now.get(name, ("gone",))[0] for name in on_edge} == on_edge, (on_edge, now)


def test_a_deleted_deployment_record_comes_back_from_an_etcd_snapshot_and_the_app_runs(chain):
    done = site_operations.backup_and_restore(chain, f"kuberos-{site_lab.FLEET}", record_name("pick-and-place"))
    assert done["backup"].returncode == 0, _tail(done["backup"])
    assert done["snapshot_mode"] == 0o600 and done["folder_mode"] == 0o700, (done["snapshot_mode"], done["folder_mode"])
    assert done["refused"].returncode != 0 and chain.figures["etcd_restore_refused_unconfirmed"], _tail(done["refused"])
    assert done["restore"].returncode == 0, _tail(done["restore"])
    assert done["restored_objects_back"] and done["nodes_ready"], {
        k: v for k, v in done.items() if k not in ("backup", "restore", "refused")
    }
    assert done["kept_old_data"] == sorted(CONTROL_PLANES), done["kept_old_data"]
    assert done["leftovers"] == [], done["leftovers"]  # no snapshot copy nor held manifest left on a control plane
    assert site_lab.etcd_members(chain.lab.machines, CONTROL_PLANES[1]) == sorted(CONTROL_PLANES)
    site_lab.wait_for("the app Ready after the restore",
                      lambda: (pods := _app_pods(chain)) and all(ready for _uid, _node, ready in pods.values()), 300)  # fmt: skip


@pytest.mark.full  # certificates.yml's renewal runs in make test on three stand-in control planes (tests/cluster)
def test_the_control_planes_certificates_renew_one_at_a_time_with_the_api_answering(chain):
    admin_before = _client_certificate_not_after(chain.lab.kubeconfig)
    result = site_operations.renew_certificates(chain)
    assert result.returncode == 0, _tail(result)
    assert chain.figures["cert_not_after_moved"], result.not_after
    assert chain.figures["api_samples_during_renew"] >= 20, chain.figures
    assert chain.figures["api_unavailable_during_renew_max_s"] <= 10, chain.figures
    # the renewed admin.conf on this machine: 0600, a later client certificate, and it works
    assert os.stat(chain.lab.kubeconfig).st_mode & 0o777 == 0o600
    assert _client_certificate_not_after(chain.lab.kubeconfig) > admin_before
    assert site_lab.nodes(chain.kube)
    assert site_operations.leftovers(chain.lab.machines) == []
    assert len(site_lab.vip_holders(chain.lab.machines, CONTROL_PLANES)) == 1
    assert site_lab.etcd_members(chain.lab.machines, CONTROL_PLANES[1]) == sorted(CONTROL_PLANES)


def test_undeploy_removes_every_pod_of_the_app(chain):
    result = chain.undeploy()
    assert result.returncode == 0, _tail(result)
    site_lab.wait_for(
        "no pod of the app", lambda: not chain.core.list_pod_for_all_namespaces(label_selector="kuberos.io/instance").items, 180
    )


def test_the_edge_worker_is_removed_cleanly_once_nothing_needs_it(chain):
    done = site_removal.remove_node(chain, EDGE_WORKER_HOST, EDGE_WORKER)
    assert done["result"].returncode == 0, _tail(done["result"])
    assert not done["node_left"] and not done["leftovers"], (EDGE_WORKER, done["leftovers"])
    assert "Delete it from the inventory now" in done["said"] and "hosts.yml" in done["said"] and done["forgotten"], done
    assert chain.figures["node_removed_clean"], chain.figures


def test_the_api_answers_through_the_virtual_ip_after_losing_its_control_plane(chain):
    # The first control plane, the special one (kubeadm init's host, the VPN's hub, the top VRRP priority), holding
    # the address: after the restore it may not (nopreempt keeps it where the first API server back took it).
    chain.hand_vip_to(CONTROL_PLANES[0])
    holder = chain.lose_vip_holder()
    assert site_lab.vip_holders(chain.lab.machines, [cp for cp in CONTROL_PLANES if cp != holder]), holder
    chain.lost_control_plane = holder


def test_the_lost_first_control_plane_rebuilt_from_a_bare_disk_joins_the_running_cluster(chain):
    lost = getattr(chain, "lost_control_plane", "")
    assert lost == CONTROL_PLANES[0], lost  # handed the virtual IP before its power was cut
    # One site.yml for two of the site's days: this control plane rebuilt, and robots off (the next test's checks).
    done = site_replace.replace_control_plane(
        chain, lost, run=lambda: chain.site_with_robots_offline(OTHER_ROBOT_MACHINE, GHOST_ROBOT, site_lab.UNUSED_ADDRESS)
    )
    chain.replaced = done
    assert done["result"].returncode == 0, _tail(done["result"])
    health = done["health"]  # a second kubeadm init would show as a one-member etcd on the rebuilt control plane
    assert set(health) == set(CONTROL_PLANES), health
    assert all(h["healthy"] and h["members"] == sorted(CONTROL_PLANES) for h in health.values()), health
    sampler = done["sampler"]
    assert sampler.samples >= 60 and sampler.holders_max == 1 and not sampler.two_holders, vars(sampler)
    found = site_lab.nodes(chain.kube)
    assert all(found[name]["ready"] for name in (*CONTROL_PLANES, CLOUD, ROBOT)), found  # the cloud VM through the new hub
    assert chain.figures["etcd_members_after_replace"] == 3 and chain.figures["vip_holders_max"] == 1, chain.figures


def test_site_yml_leaves_a_powered_off_robot_and_one_that_never_joined_and_says_so_once(chain):
    result = chain.replaced["result"]  # the run that also joined the rebuilt control plane
    assert result.returncode == 0, _tail(result)
    assert len(result.said) == 1 and OTHER_ROBOT in result.said[0] and GHOST_ROBOT in result.said[0], result.said
    assert ROBOT not in result.said[0], result.said  # a robot that is on: reached and finished
    found = site_lab.nodes(chain.kube)
    assert GHOST_ROBOT not in found and OTHER_ROBOT in found, sorted(found)  # no Node without a kubelet behind it
    assert EDGE_WORKER not in found and site_lab.NEW_ROBOT not in found, sorted(found)  # removed and forgotten: not joined again
    assert chain.figures["site_run_with_robot_offline_ok"], chain.figures


@pytest.mark.full  # make test: remove_node.yml resets two machines with the same role (node_reset) above
def test_reset_yml_takes_the_site_apart(chain):
    done = site_removal.reset_site(chain, site_removal.inventory_name(CONTROL_PLANES[0]), sorted(chain.lab.machines.machines))
    assert done["result"].returncode == 0, _tail(done["result"])
    assert len(done["running"]) == 7 and not any(done["leftovers"].values()), done["leftovers"]
    off = [m for m in chain.lab.machines.machines if m not in done["running"]]  # the robot powered off before
    assert off == [OTHER_ROBOT_MACHINE], (off, done["running"])
    assert OTHER_ROBOT in done["result"].stdout.split("Not reset")[-1], done["result"].stdout[-2000:]
    assert not site_lab.vip_holders(chain.lab.machines, done["running"]) and not done["kubeconfig_left"]
    assert chain.figures["site_reset_clean"], chain.figures


def test_teardown_leaves_the_host_as_it_was(chain):
    chain.lab.down(remove=True)
    after = snapshot_host()
    changed = snapshot_changes(chain.before, after)
    assert not changed, json.dumps(changed, indent=1)[:6000]
