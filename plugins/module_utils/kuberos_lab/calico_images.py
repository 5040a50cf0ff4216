"""Calico's three images (node, cni, kube-controllers), built on this machine from the programs
``roles/local_cluster/files/build-calico.sh`` builds from Calico's Go sources, as upstream's Dockerfiles lay them out.

A real site pulls ``quay.io/calico/{node,cni,kube-controllers}`` (or its mirror's copies). The lab cannot, so it
builds them here under those names, with the built version as the tag (``calico_version`` names it), and preloads
them into the lab machines' containerd (``node_prereqs_image_archives``) with the images kubeadm runs.

``<registry>/node:<version>``
    Debian bookworm minbase with what a VXLAN-mode calico-node runs besides itself: runit (runsvdir, sv, svlogd),
    iptables (nft and legacy), ipset, iproute2, conntrack, kmod, procps, net-tools; Calico's own
    ``node/filesystem`` (``/etc/rc.local``, ``/etc/service/available/*``, ``/etc/calico/felix.cfg``,
    ``/usr/sbin/start_runit``...) from the same source tree; ``/bin/calico-node``. ``SVDIR=/etc/service/enabled``,
    command ``start_runit``: upstream's contract, so the calico role's DaemonSet runs it unchanged. No BIRD (VXLAN
    needs no BGP) and no eBPF tools (the programs are built without cgo; the iptables dataplane runs).
``<registry>/cni:<version>``
    ``/opt/cni/bin/install`` (the install-cni init container), ``calico`` and ``calico-ipam`` (one program, acting by
    its name), and the reference plugins Calico's image ships (portmap, loopback, host-local, bandwidth, tuning);
    command ``/opt/cni/bin/install``.
``<registry>/kube-controllers:<version>``
    ``/usr/bin/kube-controllers`` (the entrypoint) and ``/usr/bin/check-status`` (its probes), ``/status/status.json``
    and ``/profiles`` owned by user 999, which it runs as (upstream's ``USER 999``).

Cached under ``<cache_dir>/images/calico/`` keyed by the recipe and the bytes; the node image's Debian root under
``<cache_dir>/images/calico/node-base-<key>/`` (a minute of debootstrap, once).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import kubeadm_images as ki
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images as li

RECIPE_VERSION = "3"
NODE_BASE_VERSION = "1"  # the node image's Debian root: its own key, so that image recipe changes do not rebuild it
DEFAULT_REGISTRY = "quay.io/calico"
DEFAULT_VERSION = "v3.28.4-11-ga0db560f05"  # build-calico.sh's label: the module proxy's one Calico commit
CNI_PLUGINS = ("portmap", "loopback", "host-local", "bandwidth", "tuning")
CNI_PLUGINS_VERSION = "v1.1.1"
NODE_PACKAGES = ("runit", "iptables", "ipset", "iproute2", "conntrack", "kmod", "procps", "net-tools", "ca-certificates")


def references(registry: str = DEFAULT_REGISTRY, version: str = DEFAULT_VERSION) -> dict[str, str]:
    return {name: f"{registry}/{name}:{version}" for name in ("node", "cni", "kube-controllers")}


def programs(cache_dir: str, version: str = DEFAULT_VERSION) -> dict[str, str]:
    """The built programs build-calico.sh leaves in ``<cache_dir>/bin``: {name: path}."""
    bin_dir = os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "bin")
    found = {
        name: os.path.join(bin_dir, f"calico-{name}-{version}")
        for name in ("node", "cni", "cni-install", "kube-controllers", "check-status")
    }
    found.update({f"plugin-{name}": os.path.join(bin_dir, f"cni-{name}-{CNI_PLUGINS_VERSION}") for name in CNI_PLUGINS})
    return found


def source_tree(cache_dir: str, version: str = DEFAULT_VERSION) -> str:
    return os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "work", f"calico-{version}", "src")


def _node_base(folder: str, log) -> str:
    """A Debian minbase root with what calico-node runs besides itself (debootstrap, cached by its recipe)."""
    key = hashlib.sha256("\0".join([NODE_BASE_VERSION, li.DEBIAN_SUITE, *NODE_PACKAGES]).encode()).hexdigest()[:12]
    base = os.path.join(folder, f"node-base-{key}")
    if os.path.exists(os.path.join(base, "done")):
        return os.path.join(base, "rootfs")
    li._require_programs("debootstrap", "unshare")
    work = base + ".tmp"
    li._remove(work)
    os.makedirs(work)
    started = time.monotonic()
    log(f"calico images: debootstrap {li.DEBIAN_SUITE} with {', '.join(NODE_PACKAGES)} for calico-node (about a minute)")
    with li._progress(log, "debootstrap for calico-node"):
        li._run(li.debootstrap_command(li.DEBIAN_SUITE, os.path.join(work, "rootfs"), li.DEBIAN_MIRROR, NODE_PACKAGES),
                what="debootstrap")  # fmt: skip
    li._strip(os.path.join(work, "rootfs"))
    with open(os.path.join(work, "done"), "w", encoding="utf-8") as handle:
        handle.write(json.dumps({"packages": NODE_PACKAGES}))
    for name in os.listdir(folder):
        if name.startswith("node-base-") and os.path.join(folder, name) not in (base, work):
            li._remove(os.path.join(folder, name))
    os.replace(work, base)
    log(f"calico images: calico-node's Debian root built in {time.monotonic() - started:.0f}s")
    return os.path.join(base, "rootfs")


def _tree_files(top: str, inside: str) -> list[tuple[str, str]]:
    found = []
    for directory, _subdirectories, files in os.walk(top):
        for name in files:
            if name == ".gitkeep":
                continue
            path = os.path.join(directory, name)
            found.append((os.path.join(inside, os.path.relpath(path, top)), path))
    return sorted(found)


def _executable(path: str, inside: str = "") -> bool:
    """A program or a script. Go's module cache keeps no execute bits, so Calico's scripts are known by their #! line
    or, as git marks them executable in Calico's tree, by where they go: /etc/rc.local (which start_runit runs and has
    no #!), /usr/sbin/*, and the runit services' run files."""
    if os.access(path, os.X_OK) or inside == "/etc/rc.local" or inside.startswith("/usr/sbin/") or inside.endswith("/run"):
        return True
    with open(path, "rb") as handle:
        return handle.read(2) == b"#!"


def _digests(files: list[tuple[str, str]]) -> list[str]:
    return [f"{inside}:{ki._file_digest(source)}:{_executable(source, inside)}" for inside, source in files]


def build(cache_dir: str, registry: str = DEFAULT_REGISTRY, version: str = DEFAULT_VERSION, log=print) -> dict[str, str]:
    """Build (or reuse) Calico's three images: {reference: OCI archive}."""
    li._require_programs("umoci")
    cache = os.path.abspath(os.path.expanduser(cache_dir))
    built = programs(cache, version)
    missing = [path for path in built.values() if not os.path.exists(path)]
    tree = os.path.join(source_tree(cache, version), "node", "filesystem")
    if missing or not os.path.isdir(tree):
        raise li.ImageBuildError(
            f"Calico's programs are not built yet ({', '.join(missing) or tree}): run roles/local_cluster/files/build-calico.sh"
        )
    images = os.path.join(cache, "images")
    folder = os.path.join(images, "calico")
    os.makedirs(os.path.join(folder, "tmp"), exist_ok=True)
    os.makedirs(os.path.join(images, "tmp"), exist_ok=True)
    wanted = references(registry, version)
    plugins = [(f"/opt/cni/bin/{name}", built[f"plugin-{name}"]) for name in CNI_PLUGINS]
    recipes = {
        "node": (
            [("/bin/calico-node", built["node"]), *_tree_files(tree, "/")],
            ["--config.env", "SVDIR=/etc/service/enabled", "--config.cmd", "start_runit"],
        ),
        "cni": (
            [("/opt/cni/bin/install", built["cni-install"]), ("/opt/cni/bin/calico", built["cni"]),
             ("/opt/cni/bin/calico-ipam", built["cni"]), *plugins],
            ["--config.env", "PATH=/opt/cni/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
             "--config.cmd", "/opt/cni/bin/install"],
        ),
        "kube-controllers": (
            [("/usr/bin/kube-controllers", built["kube-controllers"]), ("/usr/bin/check-status", built["check-status"])],
            ["--config.entrypoint", "/usr/bin/kube-controllers", "--config.user", "999"],
        ),
    }  # fmt: skip
    found = {}
    with li._locked(images, log):
        for name, reference in wanted.items():
            files, config = recipes[name]
            if name == "node":  # start_runit and the scripts of filesystem/sbin live in /usr/sbin, as upstream copies them
                files = [(re.sub(r"^/sbin/", "/usr/sbin/", inside), source) for inside, source in files]
            key = li._sha256(RECIPE_VERSION, reference, json.dumps(config), *_digests(files))[:12]
            archive = os.path.join(folder, f"{name}-{version}-{key}.tar")
            if os.path.exists(archive):
                os.utime(archive)
            else:
                started = time.monotonic()
                base = _node_base(folder, log) if name == "node" else None
                work = os.path.join(images, "tmp", f"calico-{name}-{os.getpid()}")
                li._remove(work)
                os.makedirs(work)
                try:
                    _build(work, reference, base, files, config, archive)
                finally:
                    li._remove(work)
                log(f"calico images: {reference} built in {time.monotonic() - started:.1f}s ({li._mib(li._size(archive))})")
            li._prune(folder, rf"{re.escape(name)}-.*-[0-9a-f]{{12}}\.tar", li.KEEP_ARCHIVES, archive, log)
            found[reference] = archive
    return found


def _build(work: str, reference: str, base: str | None, files, config: list[str], archive: str) -> None:
    layout, bundle = os.path.join(work, "layout"), os.path.join(work, "bundle")
    li._run(["umoci", "init", "--layout", layout])
    li._run(["umoci", "new", "--image", f"{layout}:image"])
    li._run(["umoci", "unpack", "--image", f"{layout}:image", bundle])
    rootfs = os.path.join(bundle, "rootfs")
    if base:
        subprocess.run(["cp", "-a", f"{base}/.", rootfs], check=True, capture_output=True)
    if base:  # Debian's runit links /etc/service into /etc/runit; Calico's image has it as a directory of its own
        service = os.path.join(rootfs, "etc", "service")
        if os.path.islink(service):
            os.unlink(service)
    for inside, source in files:
        target = ki.inside(rootfs, inside)
        os.makedirs(os.path.dirname(target), exist_ok=True)
        shutil.copyfile(source, target)
        os.chmod(target, 0o755 if _executable(source, inside) else 0o644)
    for directory in ("tmp", "status", "profiles", "var/lib/calico", "var/run/calico", "var/log/calico"):
        os.makedirs(os.path.join(rootfs, directory), exist_ok=True)
    os.chmod(os.path.join(rootfs, "tmp"), 0o1777)
    for path in ("status/status.json", "profiles/mem.pprof", "profiles/cpu.pprof"):  # kube-controllers runs as 999
        with open(os.path.join(rootfs, path), "w", encoding="utf-8"):
            pass
        os.chown(os.path.join(rootfs, path), 999, 0)
    li._normalise(rootfs, 0)
    history = ("--history.created_by", f"kuberos calico_images {reference}")
    li._run(["umoci", "repack", "--image", f"{layout}:image", *li.CREATED, *history, bundle])
    env = [] if any(item.startswith("PATH=") for item in config) else ["--config.env", ki.PATH_ENV]
    li._run(["umoci", "config", "--image", f"{layout}:image", "--created", li.SOURCE_DATE, *env, *config, "--no-history"])
    li._write_archive(layout, "image", reference, archive)
