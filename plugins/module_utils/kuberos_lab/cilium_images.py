"""Cilium's two images (the agent's and the generic operator's), built on this machine from the programs
``roles/local_cluster/files/build-cilium.sh`` builds from Cilium's Go module, laid out as upstream's images are.

A real site pulls ``quay.io/cilium/cilium`` and ``quay.io/cilium/operator-generic`` (or its mirror's copies). The lab
cannot, so it builds them here under those names, with the release as the tag (``cilium_version`` names it), and
preloads them into the lab machines' containerd (``node_prereqs_image_archives``) with the images kubeadm runs.

``<registry>/cilium:<version>``
    Debian bookworm minbase with what the agent runs besides itself: clang (it compiles its datapath when it starts),
    bpftool (its kernel feature probe), iproute2, iptables (nft and legacy), ipset, kmod, ca-certificates;
    ``/usr/bin/cilium-agent``; the datapath's C sources (``bpf/`` of the same module) in ``/var/lib/cilium/bpf``,
    where the agent looks for them; the CNI plugin ``/opt/cni/bin/cilium-cni``, the loopback plugin ``/cni/loopback``
    and upstream's ``/install-plugin.sh`` (from the module), which the install-cni init container runs. No Envoy (the
    L7 proxy is off) and no Hubble.
``<registry>/operator-generic:<version>``
    ``/usr/bin/cilium-operator-generic`` alone (a static program) with CA certificates.

Cached under ``<cache_dir>/images/cilium/`` keyed by the recipe and the bytes; the agent image's Debian root under
``<cache_dir>/images/cilium/agent-base-<key>/`` (debootstrap, once).
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

RECIPE_VERSION = "2"
AGENT_BASE_VERSION = "1"  # the agent image's Debian root: its own key, so that image recipe changes do not rebuild it
DEFAULT_REGISTRY = "quay.io/cilium"
DEFAULT_VERSION = "v1.15.19"  # build-cilium.sh's default: the release the Go module proxy serves
CNI_PLUGINS_VERSION = "v1.6.0"
MODULE = "github.com/cilium/cilium"
AGENT_PACKAGES = ("clang-14", "bpftool", "iproute2", "iptables", "ipset", "kmod", "ca-certificates")
IMAGES = {"agent": "cilium", "operator": "operator-generic"}


def references(registry: str = DEFAULT_REGISTRY, version: str = DEFAULT_VERSION) -> dict[str, str]:
    """{"agent": ..., "operator": ...}: the images' names, as the cilium role's ``cilium_image_registry`` forms them."""
    return {role: f"{registry}/{name}:{version}" for role, name in IMAGES.items()}


def programs(cache_dir: str, version: str = DEFAULT_VERSION) -> dict[str, str]:
    """The built programs build-cilium.sh leaves in ``<cache_dir>/bin``: {name: path}."""
    bin_dir = os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "bin")
    found = {name: os.path.join(bin_dir, f"cilium-{name}-{version}") for name in ("agent", "operator-generic", "cni")}
    found["loopback"] = os.path.join(bin_dir, f"cni-loopback-{CNI_PLUGINS_VERSION}")
    return found


def module_dir(cache_dir: str, version: str = DEFAULT_VERSION) -> str:
    """Cilium's module in the shared Go module cache (build-cilium.sh downloaded it)."""
    return os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "go", "mod", f"{MODULE}@{version}")


def _agent_base_key() -> str:
    return hashlib.sha256("\0".join([AGENT_BASE_VERSION, li.DEBIAN_SUITE, *AGENT_PACKAGES]).encode()).hexdigest()[:12]


def _agent_base(folder: str, log) -> str:
    """A Debian minbase root with what the agent runs besides itself (debootstrap, cached by its recipe)."""
    base = os.path.join(folder, f"agent-base-{_agent_base_key()}")
    if os.path.exists(os.path.join(base, "done")):
        return os.path.join(base, "rootfs")
    li._require_programs("debootstrap", "unshare")
    work = base + ".tmp"
    li._remove(work)
    os.makedirs(work)
    started = time.monotonic()
    log(f"cilium images: debootstrap {li.DEBIAN_SUITE} with {', '.join(AGENT_PACKAGES)} for the agent (a minute or two)")
    with li._progress(log, "debootstrap for cilium-agent"):
        li._run(li.debootstrap_command(li.DEBIAN_SUITE, os.path.join(work, "rootfs"), li.DEBIAN_MIRROR, AGENT_PACKAGES),
                what="debootstrap")  # fmt: skip
    li._strip(os.path.join(work, "rootfs"))
    with open(os.path.join(work, "done"), "w", encoding="utf-8") as handle:
        handle.write(json.dumps({"packages": AGENT_PACKAGES}))
    for name in os.listdir(folder):
        if name.startswith("agent-base-") and os.path.join(folder, name) not in (base, work):
            li._remove(os.path.join(folder, name))
    os.replace(work, base)
    log(f"cilium images: the agent's Debian root built in {time.monotonic() - started:.0f}s")
    return os.path.join(base, "rootfs")


def _tree_files(top: str, inside: str) -> list[tuple[str, str]]:
    found = []
    for directory, _subdirectories, files in os.walk(top):
        for name in files:
            path = os.path.join(directory, name)
            found.append((os.path.join(inside, os.path.relpath(path, top)), path))
    return sorted(found)


def _digests(files: list[tuple[str, str]]) -> list[str]:
    return [f"{inside}:{ki._file_digest(source)}" for inside, source in files]


def _executable(inside: str) -> bool:
    return inside.startswith(("/usr/bin/", "/opt/cni/bin/", "/cni/")) or inside == "/install-plugin.sh"


def build(cache_dir: str, registry: str = DEFAULT_REGISTRY, version: str = DEFAULT_VERSION, log=print) -> dict[str, str]:
    """Build (or reuse) Cilium's two images: {reference: OCI archive}."""
    li._require_programs("umoci")
    cache = os.path.abspath(os.path.expanduser(cache_dir))
    built = programs(cache, version)
    module = module_dir(cache, version)
    missing = [path for path in built.values() if not os.path.exists(path)]
    if missing or not os.path.isdir(os.path.join(module, "bpf")):
        raise li.ImageBuildError(
            f"Cilium's programs are not built yet ({', '.join(missing) or module}): run roles/local_cluster/files/build-cilium.sh"
        )
    images = os.path.join(cache, "images")
    folder = os.path.join(images, "cilium")
    os.makedirs(os.path.join(images, "tmp"), exist_ok=True)
    os.makedirs(os.path.join(folder, "tmp"), exist_ok=True)  # the archives' temporary files
    wanted = references(registry, version)
    recipes = {
        "agent": (
            [("/usr/bin/cilium-agent", built["agent"]), ("/opt/cni/bin/cilium-cni", built["cni"]),
             ("/cni/loopback", built["loopback"]),
             ("/install-plugin.sh", os.path.join(module, "plugins", "cilium-cni", "install-plugin.sh")),
             *_tree_files(os.path.join(module, "bpf"), "/var/lib/cilium/bpf")],
            ["--config.env", "INITSYSTEM=SYSTEMD", "--config.workingdir", "/home/cilium",
             "--config.cmd", "/usr/bin/cilium-agent"],
        ),
        "operator": (
            [("/usr/bin/cilium-operator-generic", built["operator-generic"])],
            ["--config.entrypoint", "/usr/bin/cilium-operator-generic"],
        ),
    }  # fmt: skip
    found = {}
    with li._locked(images, log):
        for role, reference in wanted.items():
            files, config = recipes[role]
            base_key = _agent_base_key() if role == "agent" else ""  # a new Debian root makes a new image
            key = li._sha256(RECIPE_VERSION, base_key, reference, json.dumps(config), *_digests(files))[:12]
            archive = os.path.join(folder, f"{role}-{version}-{key}.tar")
            if os.path.exists(archive):
                os.utime(archive)
            else:
                started = time.monotonic()
                base = _agent_base(folder, log) if role == "agent" else None
                work = os.path.join(images, "tmp", f"cilium-{role}-{os.getpid()}")
                li._remove(work)
                os.makedirs(work)
                try:
                    _build(work, reference, base, files, config, archive)
                finally:
                    li._remove(work)
                log(f"cilium images: {reference} built in {time.monotonic() - started:.1f}s ({li._mib(li._size(archive))})")
            li._prune(folder, rf"{re.escape(role)}-.*-[0-9a-f]{{12}}\.tar", li.KEEP_ARCHIVES, archive, log)
            found[reference] = archive
    return found


# What clang-14's packages bring that compiling the datapath never reads (it builds with -nostdinc for the bpf target
# and links nothing): the C interface library, the sanitizers' runtimes, gcc's support files and the C headers.
TRIMMED = ("usr/lib/gcc", "usr/include")
TRIMMED_LIBRARIES = re.compile(r"lib(clang-14\.so.*|[a-z]*san\.so.*)$")


def _trim(rootfs: str) -> None:
    for relative in TRIMMED:
        li._remove(os.path.join(rootfs, relative))
    libraries = os.path.join(rootfs, "usr", "lib", "x86_64-linux-gnu")
    for name in os.listdir(libraries) if os.path.isdir(libraries) else []:
        if TRIMMED_LIBRARIES.match(name):
            os.unlink(os.path.join(libraries, name))


def _build(work: str, reference: str, base: str | None, files, config: list[str], archive: str) -> None:
    layout, bundle = os.path.join(work, "layout"), os.path.join(work, "bundle")
    li._run(["umoci", "init", "--layout", layout])
    li._run(["umoci", "new", "--image", f"{layout}:image"])
    li._run(["umoci", "unpack", "--image", f"{layout}:image", bundle])
    rootfs = os.path.join(bundle, "rootfs")
    if base:
        subprocess.run(["cp", "-a", f"{base}/.", rootfs], check=True, capture_output=True)
        clang = os.path.join(rootfs, "usr", "bin", "clang")  # Debian names it clang-14; the agent runs `clang`
        if not os.path.lexists(clang):
            os.symlink("clang-14", clang)
        _trim(rootfs)
    else:  # the operator talks TLS to the API server: the host's CA bundle is not needed, but a CA directory is
        os.makedirs(os.path.join(rootfs, "etc", "ssl", "certs"), exist_ok=True)
    for inside, source in files:
        target = ki.inside(rootfs, inside)
        os.makedirs(os.path.dirname(target), exist_ok=True)
        shutil.copyfile(source, target)
        os.chmod(target, 0o755 if _executable(inside) else 0o644)
    for directory in ("tmp", "home/cilium", "var/run/cilium"):
        os.makedirs(os.path.join(rootfs, directory), exist_ok=True)
    os.chmod(os.path.join(rootfs, "tmp"), 0o1777)
    li._normalise(rootfs, 0)
    history = ("--history.created_by", f"kuberos cilium_images {reference}")
    li._run(["umoci", "repack", "--image", f"{layout}:image", *li.CREATED, *history, bundle])
    env = [] if any(item.startswith("PATH=") for item in config) else ["--config.env", ki.PATH_ENV]
    li._run(["umoci", "config", "--image", f"{layout}:image", "--created", li.SOURCE_DATE, *env, *config, "--no-history"])
    li._write_archive(layout, "image", reference, archive)
