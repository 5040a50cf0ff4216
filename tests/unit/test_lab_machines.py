"""The lab machines' and kubeadm images' pure parts: names, references, the inventory the lab writes."""

from __future__ import annotations

import pytest
import yaml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import kubeadm_images, machines


def test_kubeadm_images_are_named_as_kubeadm_names_them():
    found = kubeadm_images.references("registry.k8s.io", "v1.34.4", "v3.5.35", "v1.14.7")
    assert found == {
        "kube-apiserver": "registry.k8s.io/kube-apiserver:v1.34.4",
        "kube-controller-manager": "registry.k8s.io/kube-controller-manager:v1.34.4",
        "kube-scheduler": "registry.k8s.io/kube-scheduler:v1.34.4",
        "kube-proxy": "registry.k8s.io/kube-proxy:v1.34.4",
        "etcd": "registry.k8s.io/etcd:3.5.35-0",
        "coredns": "registry.k8s.io/coredns/coredns:v1.14.7",
        "pause": "registry.k8s.io/pause:3.10.1",
    }
    # a mirror holds CoreDNS without the extra path segment, as kubeadm asks for it there
    mirror = kubeadm_images.references("mirror.site.example:5000/k8s", "v1.34.4", "v3.5.35", "v1.14.7")
    assert mirror["coredns"] == "mirror.site.example:5000/k8s/coredns:v1.14.7"


def test_the_etcd_image_carries_etcds_own_tools_as_upstreams_does():
    """registry.k8s.io/etcd holds etcdctl and etcdutl beside etcd; so does the lab's (the backup runs etcdctl in the
    pod, the restore etcdutl from the image)."""
    built = {name: f"/cache/bin/{name}-v3.5.35" for name in ("etcd", "etcdctl", "etcdutl")}
    assert kubeadm_images.image_files("etcd", built) == [
        ("/usr/local/bin/etcd", "/cache/bin/etcd-v3.5.35"),
        ("/usr/local/bin/etcdctl", "/cache/bin/etcdctl-v3.5.35"),
        ("/usr/local/bin/etcdutl", "/cache/bin/etcdutl-v3.5.35"),
    ]
    assert kubeadm_images.image_files("coredns", {"coredns": "/c"}) == [("/coredns", "/c")]
    assert kubeadm_images.image_files("kube-apiserver", {"kube-apiserver": "/a"}) == [("/usr/local/bin/kube-apiserver", "/a")]


def test_pinned_versions_are_the_local_clusters():
    versions = kubeadm_images.pinned_versions()
    assert set(versions) == {"kubernetes", "etcd", "coredns"}
    assert all(value.startswith("v") for value in versions.values())


def test_link_names_fit_the_kernels_limit_and_are_stable(tmp_path):
    lab = machines.MachineLab(str(tmp_path), tag="km")
    assert lab.veth("edge-1") == "kmv-edge-1"
    long = lab.veth("a-very-long-machine-name")
    assert len(long) <= 15 and long == machines.MachineLab(str(tmp_path), tag="km").veth("a-very-long-machine-name")
    assert lab.netns("edge-1") == "km-edge-1" and lab.cgroup("edge-1") == "kuberos-lab-km/edge-1"


def test_the_inventory_reaches_machines_as_a_non_root_user_with_become(tmp_path):
    lab = machines.MachineLab(str(tmp_path), tag="km", subnet="10.214.0")
    lab.machines = {
        "edge-1": machines.Machine("edge-1", ["edge", "control_plane"], "10.214.0.11", host_key="ssh-ed25519 AAAA1"),
        "fetch-1": machines.Machine("fetch-1", ["robots"], "10.214.0.12", host_key="ssh-ed25519 AAAA2"),
    }
    lab.write_inventory()
    lab.write_known_hosts()
    inventory = yaml.safe_load((tmp_path / "inventory.yml").read_text())
    assert inventory["all"]["vars"]["ansible_user"] == "kuberos" and inventory["all"]["vars"]["ansible_become"] is True
    assert "StrictHostKeyChecking=yes" in inventory["all"]["vars"]["ansible_ssh_common_args"]
    assert set(inventory["all"]["children"]) == {"edge", "control_plane", "robots"}
    assert inventory["all"]["children"]["robots"]["hosts"]["fetch-1"]["ansible_host"] == "10.214.0.12"
    assert (tmp_path / "known_hosts").read_text().splitlines() == [
        "10.214.0.11 ssh-ed25519 AAAA1", "10.214.0.12 ssh-ed25519 AAAA2",
    ]  # fmt: skip


def test_the_machine_image_is_keyed_by_its_recipe():
    assert len(machines.image_key()) == 12 and machines.image_key() == machines.image_key()
    assert "containerd" in machines.PACKAGES and "python3-apt" in machines.PACKAGES


def test_image_files_never_land_outside_the_image(tmp_path):
    """An absolute symlink in a base root (Debian's /etc/service -> runit's) resolves against this machine: refused."""
    import pytest

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_images import ImageBuildError

    rootfs = tmp_path / "rootfs"
    (rootfs / "etc" / "runit").mkdir(parents=True)
    (rootfs / "etc" / "runit" / "current").symlink_to(tmp_path / "outside")
    (rootfs / "etc" / "service").symlink_to("runit/current")
    (rootfs / "usr" / "bin").mkdir(parents=True)
    (rootfs / "bin").symlink_to("usr/bin")  # merged /usr: relative, stays inside
    assert kubeadm_images.inside(str(rootfs), "/usr/bin/cilium-agent") == str(rootfs / "usr" / "bin" / "cilium-agent")
    with pytest.raises(ImageBuildError, match="outside the image"):
        kubeadm_images.inside(str(rootfs), "/etc/service/available/felix/run")


def test_the_longest_outage_runs_from_the_first_unanswered_sample_to_the_next_answer():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_operations import longest_outage

    assert longest_outage([]) == 0.0 and longest_outage([(0.0, True), (0.5, True)]) == 0.0
    samples = [(0.0, True), (0.5, False), (1.0, False), (1.5, True), (2.0, False), (2.5, True)]
    assert longest_outage(samples) == 1.0  # 0.5 -> 1.5; the second outage is 0.5
    assert longest_outage([(0.0, True), (0.5, False), (3.0, False)]) == 2.5  # never answered again: to the last sample


def test_a_playbook_past_its_time_limit_is_stopped_with_every_process_it_started(tmp_path):
    # A stand-in for ansible-playbook whose forked worker holds the output's pipe and waits forever, as a worker does
    # on a connection through a virtual IP that moved: subprocess.run's own timeout would wait on that pipe for ever.
    import os
    import subprocess
    import sys
    import time

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_lab import run_bounded

    marker = tmp_path / "worker.pid"
    script = (
        "import os, sys, time\n"
        "print('PLAY [all]', flush=True)\n"
        "if os.fork() == 0:\n"
        f"    open({str(marker)!r}, 'w').write(str(os.getpid())); time.sleep(600)\n"
        "time.sleep(600)\n"
    )
    started = time.monotonic()
    done = run_bounded([sys.executable, "-c", script], 2)
    assert time.monotonic() - started < 20
    assert done.returncode == 124 and "PLAY [all]" in done.stdout and "stopped after 2 s" in done.stdout, done
    worker = int(marker.read_text())
    time.sleep(0.5)
    assert not os.path.exists(f"/proc/{worker}") or _process_state(worker) == "Z", f"the forked worker {worker} still runs"
    quick = run_bounded([sys.executable, "-c", "print('ok')"], 30)
    assert quick.returncode == 0 and quick.stdout == "ok\n" and isinstance(quick, subprocess.CompletedProcess)


def _process_state(pid: int) -> str:
    with open(f"/proc/{pid}/stat", encoding="utf-8") as stat:
        return stat.read().rsplit(") ", 1)[-1][:1]


def test_a_lab_left_up_by_an_interrupted_run_is_refused_before_anything_is_made(tmp_path, monkeypatch):
    lab = machines.MachineLab(str(tmp_path / "state"), tag="zq")
    lab.machines["edge-a"] = machines.Machine("edge-a", ["control_plane"], "10.0.0.11", uuid="u")  # this lab's own
    present = {"/var/run/netns/zq-edge-a", "/var/run/netns/zq-fetch-01"}
    monkeypatch.setattr(machines.os.path, "exists", lambda path: path in present)
    assert lab.stale(["fetch-01", "fetch-02"]) == ["zq-fetch-01"]
    monkeypatch.setattr(machines, "missing_requirements", lambda: [])
    made = []
    monkeypatch.setattr(machines, "build_image", lambda *args: made.append("image"))
    with pytest.raises(machines.MachineError) as refused:
        lab.up([("edge-a", ["control_plane"]), ("fetch-01", ["robots"])], log=made.append)
    said = str(refused.value)
    assert "zq-fetch-01" in said and "zq-edge-a" not in said and " down --state" in said, said
    assert made == [] and not (tmp_path / "state").exists()


def test_a_host_snapshots_difference_names_the_leftovers_not_two_lists():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import snapshot_changes

    before = {"cgroups": ["cpu/user.slice", "cpu/k8s.io"], "sysctls": {"net.ipv4.ip_forward": "0"}, "links": ["lo"]}
    after = {"cgroups": ["cpu/k8s.io", "cpu/user.slice", "memory/k8s.io"], "sysctls": {"net.ipv4.ip_forward": "1"}}
    after["links"] = ["lo"]
    assert snapshot_changes(before, after) == {
        "cgroups": {"gone": [], "new": ["memory/k8s.io"]},
        "sysctls": {"gone": ["net.ipv4.ip_forward=0"], "new": ["net.ipv4.ip_forward=1"]},
    }
    assert snapshot_changes(before, dict(before)) == {}
