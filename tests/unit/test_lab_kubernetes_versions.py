"""The lab's site at an older Kubernetes release than the pinned one (to test an upgrade to the pinned one on it):
kubeadm's image names per release, and what `machines.site_vars` chooses, with the image builders stood in for (no
built programs, no machines)."""

from __future__ import annotations

import os
import re

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import (
    cilium_images,
    kubeadm_images,
    machines,
    site_lab,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images as li

PINNED = kubeadm_images.pinned_versions()
OLDER = "v1.33.7"


def test_kubeadm_133_names_pause_310_and_134_pause_3101():
    """As `kubeadm config images list` of each release names them (kubeadm's preflight pulls the pause image)."""
    older = kubeadm_images.references("registry.k8s.io", OLDER, "v3.5.35", "v1.14.7")
    assert older == {
        "kube-apiserver": "registry.k8s.io/kube-apiserver:v1.33.7",
        "kube-controller-manager": "registry.k8s.io/kube-controller-manager:v1.33.7",
        "kube-scheduler": "registry.k8s.io/kube-scheduler:v1.33.7",
        "kube-proxy": "registry.k8s.io/kube-proxy:v1.33.7",
        "etcd": "registry.k8s.io/etcd:3.5.35-0",
        "coredns": "registry.k8s.io/coredns/coredns:v1.14.7",
        "pause": "registry.k8s.io/pause:3.10",
    }
    pinned = kubeadm_images.references("registry.k8s.io", "v1.34.4", "v3.5.35", "v1.14.7")
    assert pinned["pause"] == f"registry.k8s.io/pause:{kubeadm_images.PAUSE_TAG}" == "registry.k8s.io/pause:3.10.1"
    # the two releases share etcd and CoreDNS; every other image differs, so both sets fit in one mirror
    assert {k for k in older if older[k] == pinned[k]} == {"etcd", "coredns"}


def test_the_pinned_release_has_a_known_pause_image_and_an_unknown_minor_is_refused():
    assert kubeadm_images.pause_tag(PINNED["kubernetes"]) == kubeadm_images.PAUSE_TAG
    assert kubeadm_images.kubernetes_minor("v1.33.7") == "1.33"
    with pytest.raises(li.ImageBuildError, match="PAUSE_TAGS"):
        kubeadm_images.pause_tag("v1.29.0")
    with pytest.raises(li.ImageBuildError, match="looks like"):
        kubeadm_images.pause_tag("1.33")


def test_build_all_names_the_build_of_an_older_releases_programs_when_they_are_missing(tmp_path):
    with pytest.raises(li.ImageBuildError, match=rf"KUBERNETES_VERSION={re.escape(OLDER)} .*build-binaries\.sh") as raised:
        kubeadm_images.build_all(str(tmp_path), kubernetes_version=OLDER)
    assert f"kube-apiserver-{OLDER}" in str(raised.value)


@pytest.fixture
def stand_ins(tmp_path, monkeypatch):
    """A cache with kubelet and kubeadm of both releases (empty files), and image builders that record their calls and
    return one archive per image reference."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for version in (OLDER, PINNED["kubernetes"]):
        for name in ("kubelet", "kubeadm"):
            (bin_dir / f"{name}-{version}").write_text("")
    calls = []

    def build_all(cache, repository=kubeadm_images.DEFAULT_REPOSITORY, log=print, kubernetes_version=None):
        calls.append(kubernetes_version)
        release = kubernetes_version or PINNED["kubernetes"]
        found = kubeadm_images.references(repository, release, PINNED["etcd"], PINNED["coredns"])
        return {reference: f"{cache}/images/kubeadm/{reference.rsplit('/', 1)[-1]}.tar" for reference in found.values()}

    monkeypatch.setattr(kubeadm_images, "build_all", build_all)
    monkeypatch.setattr(cilium_images, "build", lambda cache, log=print: {"quay.io/cilium/cilium:x": f"{cache}/cilium.tar"})
    monkeypatch.setattr(kubeadm_images, "build_toolbox", lambda cache, log=print: ("kuberos.local/toolbox:t", f"{cache}/tb.tar"))
    return tmp_path, calls


def test_site_vars_without_a_version_are_the_pinned_releases_as_before(stand_ins):
    cache, calls = stand_ins
    chosen = machines.site_vars(str(cache), log=lambda _m: None)
    assert calls == [None]
    assert chosen["kuberos_kubernetes_version"] == PINNED["kubernetes"]
    assert chosen["node_prereqs_kubernetes_binaries"] == {
        name: os.path.join(cache, "bin", f"{name}-{PINNED['kubernetes']}") for name in ("kubelet", "kubeadm")
    }
    assert "kuberos_lab_upgrade_binaries" not in chosen
    archives = [os.path.basename(a) for a in chosen["node_prereqs_image_archives"]]
    assert "pause:3.10.1.tar" in archives and f"kube-apiserver:{PINNED['kubernetes']}.tar" in archives
    assert not any(OLDER in a for a in archives)


def test_site_vars_at_an_older_release_carry_both_releases_images_and_the_upgrades_programs(stand_ins):
    cache, calls = stand_ins
    chosen = machines.site_vars(str(cache), log=lambda _m: None, kubernetes_version=OLDER)
    assert calls == [OLDER, None]
    assert chosen["kuberos_kubernetes_version"] == OLDER
    assert chosen["kuberos_etcd_image_tag"] == kubeadm_images.etcd_tag(PINNED["etcd"])
    assert chosen["node_prereqs_kubernetes_binaries"] == {
        name: os.path.join(cache, "bin", f"{name}-{OLDER}") for name in ("kubelet", "kubeadm")
    }
    assert chosen["kuberos_lab_upgrade_binaries"] == {
        name: os.path.join(cache, "bin", f"{name}-{PINNED['kubernetes']}") for name in ("kubelet", "kubeadm")
    }
    archives = {os.path.basename(a) for a in chosen["node_prereqs_image_archives"]}
    for version in (OLDER, PINNED["kubernetes"]):
        for name in ("kube-apiserver", "kube-controller-manager", "kube-scheduler", "kube-proxy"):
            assert f"{name}:{version}.tar" in archives
    assert {"pause:3.10.tar", "pause:3.10.1.tar", "cilium.tar", "tb.tar"} <= archives
    assert len(chosen["node_prereqs_image_archives"]) == len(archives)  # etcd and CoreDNS once


def test_the_upgrade_programs_include_kubectl_when_it_is_built(stand_ins):
    cache, _calls = stand_ins
    (cache / "bin" / f"kubectl-{PINNED['kubernetes']}").write_text("")
    chosen = machines.site_vars(str(cache), log=lambda _m: None, kubernetes_version=OLDER)
    assert chosen["kuberos_lab_upgrade_binaries"]["kubectl"] == os.path.join(cache, "bin", f"kubectl-{PINNED['kubernetes']}")


def test_site_vars_refuse_a_newer_release_and_name_the_build_of_missing_programs(stand_ins):
    cache, _calls = stand_ins
    with pytest.raises(machines.MachineError, match="older release"):
        machines.site_vars(str(cache), log=lambda _m: None, kubernetes_version="v1.35.0")
    with pytest.raises(machines.MachineError, match=r"KUBERNETES_VERSION=v1\.33\.6 .*build-binaries\.sh"):
        machines.site_vars(str(cache), log=lambda _m: None, kubernetes_version="v1.33.6")
    os.remove(cache / "bin" / f"kubeadm-{PINNED['kubernetes']}")
    with pytest.raises(machines.MachineError, match=f"kubeadm-{PINNED['kubernetes']}"):
        machines.site_vars(str(cache), log=lambda _m: None, kubernetes_version=OLDER)


def test_the_site_chain_takes_its_release_from_the_environment(monkeypatch):
    monkeypatch.delenv(site_lab.KUBERNETES_VERSION_ENV, raising=False)
    assert site_lab.site_kubernetes_version() is None
    monkeypatch.setenv(site_lab.KUBERNETES_VERSION_ENV, "")
    assert site_lab.site_kubernetes_version() is None
    monkeypatch.setenv(site_lab.KUBERNETES_VERSION_ENV, OLDER)
    assert site_lab.site_kubernetes_version() == OLDER
