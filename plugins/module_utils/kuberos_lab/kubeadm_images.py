"""The images kubeadm runs (control plane, etcd, kube-proxy, CoreDNS, pause), built on this machine from the
programs the project builds from the Go module proxy, as OCI image archives named as kubeadm names them.

A real site pulls these images from ``registry.k8s.io`` or from its mirror (``kuberos_kubeadm_image_repository``).
The lab cannot reach either, so it builds them from the same sources at the pinned versions and preloads them into
each machine's containerd (the ``node_prereqs`` role's ``node_prereqs_image_archives``, the way an air-gapped site
preloads the archives it carried in). kubeadm's static pods and add-ons then find them under the names they expect
and never pull (``imagePullPolicy: IfNotPresent``).

One image per program, one layer each, as upstream's distroless images are made:

``<repository>/kube-apiserver``, ``kube-controller-manager``, ``kube-scheduler`` (tag: the Kubernetes version)
    the static program at ``/usr/local/bin/<name>`` (kubeadm's static pods run ``<name>`` from PATH).
``<repository>/etcd:<etcd version>-0``
    ``/usr/local/bin/etcd`` with etcd's own tools beside it, ``etcdctl`` and ``etcdutl`` (as upstream's image: the
    site's backup runs etcdctl inside the etcd pod, its restore etcdutl from this image); the tag is etcd's version
    in kubeadm's form (``3.5.35-0``). kubeadm's default etcd for Kubernetes 1.34 is 3.6; the project builds etcd
    3.5, which Kubernetes 1.34 supports, so the site's ClusterConfiguration names it (``kuberos_etcd_image_tag``).
``<repository>/kube-proxy``
    ``/usr/local/bin/kube-proxy`` plus this machine's ``iptables`` (the nft and legacy variants, with
    iptables-restore and -save), ``conntrack`` and the shared libraries they load, found with ``ldd``: what
    upstream's distroless-iptables base holds for kube-proxy.
``<repository>/coredns/coredns:<CoreDNS version>`` (``<repository>/coredns:<version>`` for a mirror)
    ``/coredns``, the entrypoint, as the published image; kubeadm's Deployment passes ``-conf``.
``<repository>/pause:<tag>``
    The project's pause image (``local_images``), under the name kubeadm of that Kubernetes minor uses
    (`PAUSE_TAGS`: ``3.10.1`` for 1.34, ``3.10`` for 1.33; the sandbox setting's default is 1.34's).

The pinned Kubernetes version is the default; an older one (``--kubernetes-version``, `build_all`'s
``kubernetes_version``) builds the control plane's and kube-proxy's images from that version's programs (built with
``KUBERNETES_VERSION=<version> roles/local_cluster/files/build-binaries.sh``) with the same etcd and CoreDNS: a lab
site at that version that an upgrade then takes to the pinned one (`machines.site_vars`).

Each archive is keyed by the recipe and the bytes it holds, cached under ``<cache_dir>/images/kubeadm/``; builds
happen in ``tmp/`` and are renamed into place. Needs root (root-owned files), umoci and ldd.

    PYTHONPATH=.collections .venv/bin/python -m \\
        ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.kubeadm_images --json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images as li

RECIPE_VERSION = "1"
DEFAULT_REPOSITORY = "registry.k8s.io"
PAUSE_TAG = "3.10.1"  # kubeadm 1.34's sandbox image
# The pause image kubeadm of each Kubernetes minor asks for (`kubeadm config images list`); kubeadm's preflight pulls
# it, so a lab site at that version needs it under this name.
PAUSE_TAGS = {"1.33": "3.10", "1.34": PAUSE_TAG}
PATH_ENV = "PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
# What kube-proxy's iptables mode runs (upstream's distroless-iptables ships these).
IPTABLES_PROGRAMS = ("/usr/sbin/xtables-nft-multi", "/usr/sbin/xtables-legacy-multi", "/usr/sbin/conntrack")
IPTABLES_LINKS = {
    "iptables": "xtables-nft-multi",
    "iptables-save": "xtables-nft-multi",
    "iptables-restore": "xtables-nft-multi",
    "ip6tables": "xtables-nft-multi",
    "ip6tables-save": "xtables-nft-multi",
    "ip6tables-restore": "xtables-nft-multi",
    "iptables-nft": "xtables-nft-multi",
    "iptables-nft-save": "xtables-nft-multi",
    "iptables-nft-restore": "xtables-nft-multi",
    "ip6tables-nft": "xtables-nft-multi",
    "ip6tables-nft-save": "xtables-nft-multi",
    "ip6tables-nft-restore": "xtables-nft-multi",
    "iptables-legacy": "xtables-legacy-multi",
    "iptables-legacy-save": "xtables-legacy-multi",
    "iptables-legacy-restore": "xtables-legacy-multi",
    "ip6tables-legacy": "xtables-legacy-multi",
    "ip6tables-legacy-save": "xtables-legacy-multi",
    "ip6tables-legacy-restore": "xtables-legacy-multi",
}


def etcd_tag(version: str) -> str:
    """kubeadm's form of an etcd image tag: ``v3.5.35`` -> ``3.5.35-0``."""
    return f"{version.lstrip('v')}-0"


def coredns_repository(repository: str) -> str:
    """kubeadm puts CoreDNS under ``coredns/coredns`` only in its default repository; a mirror holds ``coredns``."""
    return f"{repository}/coredns/coredns" if repository == DEFAULT_REPOSITORY else f"{repository}/coredns"


def kubernetes_minor(kubernetes_version: str) -> str:
    """``v1.33.7`` -> ``1.33``."""
    match = re.fullmatch(r"v(1\.\d+)\.\d+", kubernetes_version)
    if not match:
        raise li.ImageBuildError(f"a Kubernetes release looks like v1.34.4, got {kubernetes_version!r}")
    return match.group(1)


def pause_tag(kubernetes_version: str) -> str:
    """The pause image's tag kubeadm of ``kubernetes_version`` names (PAUSE_TAGS)."""
    minor = kubernetes_minor(kubernetes_version)
    if minor not in PAUSE_TAGS:
        raise li.ImageBuildError(
            f"which pause image kubeadm {minor} asks for is not known here: add it to kubeadm_images.PAUSE_TAGS "
            f"(kubeadm config images list --kubernetes-version {kubernetes_version})"
        )
    return PAUSE_TAGS[minor]


def references(repository: str, kubernetes_version: str, etcd_version: str, coredns_version: str) -> dict[str, str]:
    """{program: image reference} for the images kubeadm of ``kubernetes_version`` runs, with the project's etcd and
    CoreDNS versions."""
    found = {
        name: f"{repository}/{name}:{kubernetes_version}"
        for name in ("kube-apiserver", "kube-controller-manager", "kube-scheduler", "kube-proxy")
    }
    found["etcd"] = f"{repository}/etcd:{etcd_tag(etcd_version)}"
    found["coredns"] = f"{coredns_repository(repository)}:{coredns_version}"
    found["pause"] = f"{repository}/pause:{pause_tag(kubernetes_version)}"
    return found


# The tools an image carries beside its program, each at /usr/local/bin/<tool>, built at the program's version.
IMAGE_TOOLS = {"etcd": ("etcdctl", "etcdutl")}


def image_files(program: str, binaries: dict[str, str]) -> list[tuple[str, str]]:
    """(path in the image, built program here) of ``program``'s image: the program (``/coredns`` for CoreDNS, as the
    published image; ``/usr/local/bin/<name>`` for the others) and its tools (IMAGE_TOOLS)."""
    path = "/coredns" if program == "coredns" else f"/usr/local/bin/{program}"
    return [(path, binaries[program]), *((f"/usr/local/bin/{tool}", binaries[tool]) for tool in IMAGE_TOOLS.get(program, ()))]


def _libraries(program: str) -> list[str]:
    """The shared libraries `program` loads (ldd), with the dynamic loader."""
    output = li._run(["ldd", program], what=f"ldd {program}")
    found = []
    for line in output.splitlines():
        match = re.search(r"(/\S+) \(0x", line)
        if match:
            found.append(match.group(1))
    return found


def _iptables_files() -> list[tuple[str, str]]:
    """(path in the image, path here) for kube-proxy's iptables, conntrack and their libraries, symlinks resolved;
    the xtables extensions iptables loads at run time included."""
    files: dict[str, str] = {}
    extensions = "/usr/lib/x86_64-linux-gnu/xtables"
    for program in IPTABLES_PROGRAMS:
        if not os.path.exists(program):
            raise li.ImageBuildError(f"kube-proxy's image needs {program} (Debian: apt-get install iptables conntrack)")
        files[program] = program
        for library in _libraries(program):
            files[library] = os.path.realpath(library)
    if os.path.isdir(extensions):
        for name in sorted(os.listdir(extensions)):
            path = os.path.join(extensions, name)
            files[path] = path
            for library in _libraries(path):
                files.setdefault(library, os.path.realpath(library))
    return sorted(files.items())


def _content_key(*parts: str | bytes) -> str:
    return li._sha256(RECIPE_VERSION, *parts)[:12]


def _file_digest(path: str) -> str:
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def inside(rootfs: str, path: str) -> str:
    """``path`` of the image under ``rootfs``, refusing a path whose directories lead out of it (an absolute symlink in
    the image resolves against this machine's root)."""
    target = os.path.join(rootfs, path.lstrip("/"))
    parent = os.path.realpath(os.path.dirname(target))
    root = os.path.realpath(rootfs)
    if parent != root and not parent.startswith(root + os.sep):
        raise li.ImageBuildError(f"{path} would be written outside the image ({parent}): a symlink in its path leads out")
    return target


def _build_one(work: str, reference: str, files: list[tuple[str, str]], links: dict[str, str], config: list[str], archive: str):
    """An image from scratch: ``files`` (image path, source) copied, ``links`` (image path: target) made, one layer."""
    layout, bundle = os.path.join(work, "layout"), os.path.join(work, "bundle")
    li._run(["umoci", "init", "--layout", layout])
    li._run(["umoci", "new", "--image", f"{layout}:image"])
    li._run(["umoci", "unpack", "--image", f"{layout}:image", bundle])
    rootfs = os.path.join(bundle, "rootfs")
    for path, source in files:
        target = inside(rootfs, path)
        os.makedirs(os.path.dirname(target), exist_ok=True)
        shutil.copyfile(source, target)
        os.chmod(target, 0o755 if os.access(source, os.X_OK) else 0o644)
    for path, pointing in links.items():
        target = inside(rootfs, path)
        os.makedirs(os.path.dirname(target), exist_ok=True)
        os.symlink(pointing, target)
    os.makedirs(os.path.join(rootfs, "tmp"), exist_ok=True)
    os.chmod(os.path.join(rootfs, "tmp"), 0o1777)
    li._normalise(rootfs, 0)
    history = ("--history.created_by", f"kuberos kubeadm_images {reference}")
    li._run(["umoci", "repack", "--image", f"{layout}:image", *li.CREATED, *history, bundle])
    li._run(["umoci", "config", "--image", f"{layout}:image", "--created", li.SOURCE_DATE, "--config.env", PATH_ENV,
             *config, "--no-history"])  # fmt: skip
    li._write_archive(layout, "image", reference, archive)


def build(
    cache_dir: str,
    binaries: dict[str, str],
    pause_archive: str,
    *,
    repository: str = DEFAULT_REPOSITORY,
    kubernetes_version: str,
    etcd_version: str,
    coredns_version: str,
    log=print,
) -> dict[str, str]:
    """Build (or reuse) every image kubeadm runs: {reference: OCI archive}. ``binaries``: program -> path of the
    built program (kube-apiserver, kube-controller-manager, kube-scheduler, kube-proxy, etcd, etcdctl, etcdutl, coredns);
    ``pause_archive``: the project's pause image (local_images), renamed."""
    li._require_programs("umoci", "ldd")
    images = os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "images")
    folder = os.path.join(images, "kubeadm")
    os.makedirs(os.path.join(images, "tmp"), exist_ok=True)
    os.makedirs(os.path.join(folder, "tmp"), exist_ok=True)
    wanted = references(repository, kubernetes_version, etcd_version, coredns_version)
    found = {}
    with li._locked(images, log):
        for program, reference in wanted.items():
            started = time.monotonic()
            links: dict[str, str] = {}
            config: list[str] = []
            if program == "pause":
                key = _content_key(reference, _file_digest(pause_archive))
            else:
                files = image_files(program, binaries)
                if program == "kube-proxy":
                    files += _iptables_files()
                    links = {f"/usr/sbin/{name}": target for name, target in IPTABLES_LINKS.items()}
                if program == "coredns":
                    config = ["--config.entrypoint", "/coredns"]
                key = _content_key(reference, json.dumps([links, config]), *(f"{i}:{_file_digest(s)}" for i, s in files))
            name = reference.rsplit("/", 1)[-1].replace(":", "-")
            archive = os.path.join(folder, f"{name}-{key}.tar")
            if os.path.exists(archive):
                os.utime(archive)
            elif program == "pause":
                _rename_archive(pause_archive, reference, archive, images)
            else:
                work = os.path.join(images, "tmp", f"kubeadm-{name}-{os.getpid()}")
                li._remove(work)
                os.makedirs(work)
                try:
                    _build_one(work, reference, files, links, config, archive)  # written in tmp/, then renamed
                finally:
                    li._remove(work)
                log(f"kubeadm images: {reference} built in {time.monotonic() - started:.1f}s ({li._mib(li._size(archive))})")
            li._prune(folder, rf"{re.escape(name)}-[0-9a-f]{{12}}\.tar", li.KEEP_ARCHIVES, archive, log)
            found[reference] = archive
    return found


def _rename_archive(source: str, reference: str, destination: str, images: str) -> None:
    """The same image under another name: the archive's index entry renamed, the blobs kept."""
    work = os.path.join(images, "tmp", f"kubeadm-pause-{os.getpid()}")
    li._remove(work)
    os.makedirs(os.path.join(work, "layout"))
    try:
        layout = os.path.join(work, "layout")
        li._run(["tar", "-xf", source, "-C", layout])
        with open(os.path.join(layout, "index.json"), encoding="utf-8") as handle:
            index = json.load(handle)
        index["manifests"][0].setdefault("annotations", {})[li.REF_ANNOTATION] = "image"
        with open(os.path.join(layout, "index.json"), "w", encoding="utf-8") as handle:
            json.dump(index, handle)
        li._write_archive(layout, "image", reference, destination)
    finally:
        li._remove(work)


TOOLBOX_IMAGE = "kuberos.local/toolbox"
BUSYBOX = "/bin/busybox"  # Debian's busybox-static: one static program with sh, wget, nc, httpd, ping ...


def build_toolbox(cache_dir: str, log=print) -> tuple[str, str]:
    """A tools image for the lab's network checks (a server and clients in pods): Debian's static busybox as
    ``/bin/busybox`` and ``/bin/sh``; tagged with busybox's version. (reference, archive)."""
    linked = subprocess.run(["ldd", BUSYBOX], capture_output=True, text=True, check=False) if os.path.exists(BUSYBOX) else None
    if linked is None or "not a dynamic executable" not in linked.stdout + linked.stderr:
        raise li.ImageBuildError(f"the toolbox image needs a static {BUSYBOX} (Debian: apt-get install busybox-static)")
    version = re.search(r"v(\d+\.\d+\.\d+)", li._run([BUSYBOX]) or "")
    reference = f"{TOOLBOX_IMAGE}:busybox-{version.group(1) if version else 'unknown'}"
    images = os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "images")
    folder = os.path.join(images, "kubeadm")
    os.makedirs(os.path.join(folder, "tmp"), exist_ok=True)
    files = [("/bin/busybox", BUSYBOX)]
    links = {"/bin/sh": "busybox"}
    key = _content_key(reference, json.dumps(links), _file_digest(BUSYBOX))
    archive = os.path.join(folder, f"toolbox-{key}.tar")
    with li._locked(images, log):
        if not os.path.exists(archive):
            work = os.path.join(images, "tmp", f"toolbox-{os.getpid()}")
            li._remove(work)
            os.makedirs(work)
            try:
                _build_one(work, reference, files, links, ["--config.cmd", "/bin/sh"], archive)
            finally:
                li._remove(work)
        li._prune(folder, r"toolbox-[0-9a-f]{12}\.tar", li.KEEP_ARCHIVES, archive, log)
    return reference, archive


REPO_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
VERSIONS_FILE = os.path.join(REPO_ROOT, "roles", "local_cluster", "defaults", "main.yml")


def pinned_versions() -> dict[str, str]:
    """The versions the project builds (the local_cluster role's defaults): kubernetes, etcd, coredns."""
    found = {}
    with open(VERSIONS_FILE, encoding="utf-8") as handle:
        for line in handle:
            match = re.match(r"^local_cluster_(kubernetes|etcd|coredns)_version: *[\"']?(v[^\"'\s]+)", line)
            if match:
                found[match.group(1)] = match.group(2)
    if set(found) != {"kubernetes", "etcd", "coredns"}:
        raise li.ImageBuildError(f"{VERSIONS_FILE}: expected local_cluster_kubernetes/etcd/coredns_version, found {found}")
    return found


def build_all(
    cache_dir: str, repository: str = DEFAULT_REPOSITORY, log=print, kubernetes_version: str | None = None
) -> dict[str, str]:
    """Every image kubeadm runs, from the built programs in ``<cache_dir>/bin``: at the pinned versions, or with
    ``kubernetes_version`` the control plane's and kube-proxy's at that release (etcd and CoreDNS stay the pinned
    ones, which the lab's site names whatever its Kubernetes version)."""
    versions = pinned_versions()
    kubernetes = kubernetes_version or versions["kubernetes"]
    pause_tag(kubernetes)  # a version whose pause image is unknown fails before anything is built
    cache = os.path.abspath(os.path.expanduser(cache_dir))
    binaries = {
        name: os.path.join(cache, "bin", f"{name}-{kubernetes}")
        for name in ("kube-apiserver", "kube-controller-manager", "kube-scheduler", "kube-proxy")
    }
    for name in ("etcd", *IMAGE_TOOLS["etcd"]):
        binaries[name] = os.path.join(cache, "bin", f"{name}-{versions['etcd']}")
    binaries["coredns"] = os.path.join(cache, "bin", f"coredns-{versions['coredns']}")
    missing = [path for path in binaries.values() if not os.path.exists(path)]
    if missing:
        hint = "make binaries WITH_NODES=1" if kubernetes == versions["kubernetes"] else build_command(kubernetes)
        raise li.ImageBuildError(f"not built yet: {', '.join(missing)} ({hint})")
    pause_archive = li.build_pause(REPO_ROOT, cache, log=log)
    return build(
        cache, binaries, pause_archive, repository=repository, kubernetes_version=kubernetes,
        etcd_version=versions["etcd"], coredns_version=versions["coredns"], log=log,
    )  # fmt: skip


def build_command(kubernetes_version: str) -> str:
    """How the programs a lab site at ``kubernetes_version`` needs are built: those of ``make binaries WITH_KUBEADM=1
    WITH_NODES=1`` at that release."""
    return (
        f"KUBERNETES_VERSION={kubernetes_version} SKIP_KUBECTL=1 SKIP_KUBEADM=0 SKIP_NODES=0 "
        "roles/local_cluster/files/build-binaries.sh"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Build the images kubeadm runs from the project's built programs.")
    parser.add_argument("--cache-dir", default=os.environ.get("KUBEROS_CACHE_DIR") or "~/.cache/kuberos")
    parser.add_argument("--repository", default=DEFAULT_REPOSITORY)
    parser.add_argument("--json", action="store_true", help="print {reference: archive} as JSON")
    parser.add_argument("--kubernetes-version", help="an older release than the pinned one (its programs built)")
    args = parser.parse_args(argv)
    log = (lambda message: print(message, file=sys.stderr)) if args.json else print
    try:
        found = build_all(args.cache_dir, args.repository, log=log, kubernetes_version=args.kubernetes_version)
    except li.ImageBuildError as error:
        print(f"kubeadm images: {error}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(found, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
