"""The collection's container images, built on this machine as OCI image archives, and imported into containerd.

The real-node tier of the local cluster (kubelets and containerd in network namespaces) cannot pull images:
everything its pods run is built here from the repository and imported into each node's containerd (or pushed
to the lab's registry, `kuberos_lab.registry`, and pulled from it). Four images:

``kuberos.local/pause:3.10``
    The pod sandbox: ``roles/local_cluster/files/pause.c`` compiled with ``gcc -static -Os`` is the only file,
    the entrypoint is ``["/pause"]``.

``kuberos.local/ros:<key>``
    One image for the collection's own programs: the pick-and-place modules (``python3 -m
    kuberos_pnp.<module>``), the gRPC bridge and the controller (``python -m ansible_collections.kuberos.
    platform.plugins.module_utils.<...>``). ROS is on its PATH (no entrypoint). `image_aliases` lists the names
    the specs and render options use for it.
    Two layers:

    base (cached, minutes to build)
        ``debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates bookworm`` (Debian's
        python3 is 3.11, as the cp311 manylinux wheels need), a venv ``/opt/ros/jazzy`` made inside the rootfs with
        the rootfs's own python3 (``chroot <rootfs> python3 -m venv --without-pip``), and the wheels installed
        into it from the host: the project venv's pip with ``--prefix <rootfs>/opt/ros/jazzy --no-deps
        --ignore-installed`` (downloads go through the host's pip cache). Which distributions: all of requirements-ros.txt,
        the ones the modules, the bridge and the controller import (`IMAGE_DISTRIBUTIONS`), and everything
        those depend on, as the project venv's installed metadata says; the versions are the pins of
        requirements-ros.txt, requirements-sim.txt and requirements.txt. toppra imports matplotlib at import
        time, so matplotlib and its dependencies are in. Scripts get ``#!/opt/ros/jazzy/bin/python3``; headers,
        the packages' ``tests`` directories, docs (not the copyright files), man pages, locales and apt lists
        go; the site-packages are byte-compiled by the venv's Python (the same 3.11 bytecode), as
        unchecked-hash pycs: layer tars round mtimes to the second, which would make timestamp pycs stale, and
        nothing must recompile at run time (the controller runs on a read-only root filesystem);
        and a chroot smoke test imports the main modules before the base is cached.
        The rootfs becomes one layer with ``umoci unpack`` / ``umoci repack``, and ``umoci config`` sets the
        environment of `plugins/module_utils/kuberos_lab/ros_wheels.ros_environment` with the image's paths (PATH starts
        with /opt/ros/jazzy/bin, so ``python``, ``python3`` and ``fast-discovery-server`` are the venv's;
        LD_LIBRARY_PATH, _ROS_WHEELS_BOOTSTRAP_COMPLETE=1) plus ROS_LOG_DIR=/tmp/ros, HOME=/tmp,
        PYTHONPATH=/opt/kuberos, RMW_IMPLEMENTATION=rmw_fastrtps_cpp, and working directory /opt/kuberos; no
        entrypoint, no command. Keyed by `RECIPE_VERSION`, the Debian suite and the pinned lines installed.

    application (seconds)
        ``/opt/kuberos/kuberos_pnp/`` from ``sim/kuberos_pnp/`` and
        ``/opt/kuberos/ansible_collections/kuberos/platform/plugins/`` from ``plugins/`` (namespace packages: no
        ``__init__.py`` is added), without ``__pycache__``: a tar written here (root-owned, fixed mtime, sorted)
        and appended with ``umoci raw add-layer``. Keyed by the files' paths, modes and contents.
        (``umoci insert`` of Debian's umoci 0.4.7 writes layer tars without their end, which containerd
        rejects; ``raw add-layer`` and ``repack`` write complete ones.)

    The tag is the first 12 hex digits of sha256(base key, application key).

``kuberos.local/ros-base:<key>``
    The published ROS image's contract (``docker.io/library/ros:jazzy-ros-base``, the discovery servers'
    default image, is an alias of it): the same base (ROS 2 under ``/opt/ros/jazzy``), a layer with
    ``/ros_entrypoint.sh`` (sources ``/opt/ros/$ROS_DISTRO/setup.bash``, then ``exec "$@"``, as the published
    one) and ``/opt/ros/jazzy/setup.bash`` (and ``setup.sh``, ``local_setup.bash``: PATH, LD_LIBRARY_PATH,
    ROS_DISTRO...), and the published configuration: only the system directories on PATH, ``ROS_DISTRO=jazzy``,
    entrypoint ``/ros_entrypoint.sh``, command ``bash``. Nothing of ROS runs unless the entrypoint runs first,
    so a rendered pod that overrode the entrypoint (``command:``) would fail here as it would on a real site.

``kuberos.local/prometheus:<key>``
    Debian's Prometheus (the ``prometheus`` package scripts/setup.sh installs on the host: one Go program linked
    against libc only) for a Prometheus in the cluster, as the published ``prom/prometheus`` image runs it: the
    same base plus a layer with ``/bin/prometheus`` and a minimal ``/etc/prometheus/prometheus.yml``; entrypoint
    ``/bin/prometheus``, command ``--config.file=/etc/prometheus/prometheus.yml --storage.tsdb.path=/prometheus``,
    user ``nobody`` (65534), working directory ``/prometheus``. Known as ``kuberos.local/prometheus:debian`` too.
    Keyed by the base and the program's bytes.

Cache, under ``<cache_dir>/images/`` (``cache_dir`` is ``~/.cache/kuberos`` or ``$KUBEROS_CACHE_DIR``):
``base-<key>/`` (the base as an OCI layout, kept for the current and one previous key), ``ros-<key>.tar``,
``pause-<key>.tar`` (the archives, the newest two of each kind kept), ``tmp/`` (builds in progress). Every
build happens in ``tmp/`` and is renamed into place when complete, so a crash leaves nothing that looks
finished. One build at a time: callers take an exclusive flock on ``images/.lock``; a caller that finds the
lock taken waits, then reuses what the other one built.

An archive is an OCI image layout in a tar (``oci-layout``, ``index.json``, the image's blobs) with one image
whose index entry carries both ``org.opencontainers.image.ref.name`` (the tag) and ``io.containerd.image.name``
(the full reference), which ``ctr images import`` uses as the image's name. `import_images` imports into the
``k8s.io`` namespace (the CRI's) and unpacks for the ``overlayfs`` snapshotter (the CRI's default), skips
images that are already there with the same digest and unpacked, tags the aliases, and labels every name
``io.cri-containerd.pinned=pinned`` (containerd 1.7 and newer keep pinned images from the kubelet's image
garbage collection; 1.6 ignores the label).

No Ansible imports and no Kubernetes client: the standard library, subprocess, and these programs: debootstrap,
chroot, umoci, gcc (with a static libc), and ctr for importing. Building needs root (debootstrap, chroot,
root-owned files in the layers). KUBEROS_DEBIAN_MIRROR overrides the Debian mirror. Prebuild from the
command line (``--json`` prints images and aliases as JSON; ``import --address <containerd socket>`` also imports):

    PYTHONPATH=.collections .venv/bin/python -m \\
        ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_images build [--cache-dir D]
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import fcntl
import functools
import glob
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.ros_wheels import ros_environment

ROS_IMAGE = "kuberos.local/ros"
# The published ROS image's contract (docker.io/library/ros:jazzy-ros-base): ROS under /opt/ros/<distro>, the
# entrypoint /ros_entrypoint.sh sources its setup.bash and execs the command, nothing of ROS on PATH before it.
ROS_BASE_IMAGE = "kuberos.local/ros-base"
ROS_DISTRO = "jazzy"
ROS_ENTRYPOINT = "/ros_entrypoint.sh"
PAUSE_IMAGE = "kuberos.local/pause:3.10"

# Part of every cache key: change it when the recipe changes what the images contain.
RECIPE_VERSION = "7"

DEBIAN_SUITE = "bookworm"
DEBIAN_PACKAGES = ("python3", "python3-venv", "ca-certificates")
DEBIAN_MIRROR = os.environ.get("KUBEROS_DEBIAN_MIRROR", "http://deb.debian.org/debian")

VENV = f"/opt/ros/{ROS_DISTRO}"  # the wheels' ROS where the published images keep theirs
APP_DIR = "/opt/kuberos"
REQUIREMENTS = ("requirements-ros.txt", "requirements-sim.txt", "requirements.txt")
INSTALL_ALL_OF = "requirements-ros.txt"
# What the image's programs import beyond requirements-ros.txt; what these need comes along (the venv's metadata).
IMAGE_DISTRIBUTIONS = (
    # the pick-and-place modules (sim/kuberos_pnp)
    "pybullet",
    "ompl",
    "toppra",
    "ros-jazzy-geometry-msgs",
    "ros-jazzy-shape-msgs",
    "ros-jazzy-trajectory-msgs",
    "ros-jazzy-visualization-msgs",
    # the gRPC bridge (plugins/module_utils/kuberos_bridge)
    "grpcio",
    "protobuf",
    "cryptography",
    "PyYAML",
    # the controller (plugins/module_utils/kuberos_controller and the kuberos core), its dashboard and /metrics
    "kubernetes",
    "jsonschema",
    "aiohttp",
    "prometheus_client",
)
# Imported in a chroot before the base is cached.
SMOKE_IMPORTS = (
    *("rclpy", "std_msgs.msg", "trajectory_msgs.msg", "visualization_msgs.msg", "pybullet", "ompl", "toppra", "scipy"),
    *("grpc", "cryptography", "yaml", "kubernetes.client", "jsonschema", "aiohttp.web", "prometheus_client"),
)

# (source in the repository, destination in the image)
APP_TREES = (
    ("sim/kuberos_pnp", f"{APP_DIR}/kuberos_pnp"),
    ("plugins", f"{APP_DIR}/ansible_collections/kuberos/platform/plugins"),
)
APP_MTIME = 946684800  # 2000-01-01: the same files make the same layer, whenever they were checked out
# Every time an image records (file times in the layers, the config's and history's created): the same sources
# give the same digests, whenever and wherever they are built.
SOURCE_DATE = "2000-01-01T00:00:00Z"
CREATED = ("--history.created", SOURCE_DATE)

PAUSE_SOURCE = "roles/local_cluster/files/pause.c"

# The application image runs as a user, not as root (the rendered pods name the same user: pod_security.DEFAULT_USER).
APP_IMAGE_CONFIG = ("--config.user", "1000:1000")
# The names the specs, the render options and the roles' defaults use for the ROS image.
ALIASES = (
    "ghcr.io/kuberos/pnp-perception:0.1",
    "ghcr.io/kuberos/pnp-planner:0.1",
    "ghcr.io/kuberos/pnp-control:0.1",
    "ghcr.io/kuberos/pnp-coordinator:0.1",
    "ghcr.io/kuberos/pnp-robot-sim:0.1",
    "ghcr.io/kuberos/bridge:0.2.0",
    "ghcr.io/kuberos/controller:0.2.0",
)
# The names under which the published-layout image is known: the discovery servers' default image.
ROS_BASE_ALIASES = (f"ros:{ROS_DISTRO}-ros-base",)
PROMETHEUS_IMAGE = "kuberos.local/prometheus"
PROMETHEUS_ALIASES = ("kuberos.local/prometheus:debian",)
PROMETHEUS_BINARY = "/usr/bin/prometheus"  # Debian's package prometheus
PROMETHEUS_CONFIG = """# kuberos local_images: a Prometheus that scrapes itself; mount the real configuration over this file.
global:
  scrape_interval: 15s
scrape_configs:
  - job_name: prometheus
    static_configs:
      - targets: ["localhost:9090"]
"""
PROMETHEUS_IMAGE_CONFIG = (
    "--clear=config.env", "--config.env", "PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
    "--config.user", "65534:65534", "--config.workingdir", "/prometheus", "--config.entrypoint", "/bin/prometheus",
    "--config.cmd", "--config.file=/etc/prometheus/prometheus.yml", "--config.cmd", "--storage.tsdb.path=/prometheus",
    "--config.exposedports", "9090/tcp",
)  # fmt: skip

NAME_ANNOTATION = "io.containerd.image.name"
REF_ANNOTATION = "org.opencontainers.image.ref.name"
PIN_LABEL = "io.cri-containerd.pinned=pinned"

KEEP_BASES = 2
KEEP_ARCHIVES = 2
BUILD_TIMEOUT = 3600


class ImageBuildError(RuntimeError):
    """A step of building or importing an image failed; the message says which and why."""


# --- helpers ---------------------------------------------------------------------------------------------------


def debootstrap_command(suite: str, target: str, mirror: str, packages: list[str] | tuple[str, ...]) -> list[str]:
    """debootstrap (minbase with ``packages``) in a mount namespace of its own: the file systems it mounts inside
    the root it builds (/proc and others) are its alone, so nothing else on this machine sees them (the host
    snapshots of the lab's tests, which run beside the builds), and they go when it exits, however it exits."""
    return [
        "unshare", "--mount", "--propagation", "private",
        "debootstrap", "--variant=minbase", f"--include={','.join(packages)}", suite, target, mirror,
    ]  # fmt: skip


def _run(command: list[str], *, timeout: float = BUILD_TIMEOUT, env: dict | None = None, what: str = "") -> str:
    """Run a command; its output (stdout and stderr together) on success, ImageBuildError with the tail if not."""
    try:
        done = subprocess.run(
            command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            timeout=timeout, env=env, umask=0o022, check=False,
        )  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as error:
        raise ImageBuildError(f"{what or command[0]}: {' '.join(command)}: {error}") from error
    output = done.stdout.decode(errors="replace")
    if done.returncode != 0:
        raise ImageBuildError(f"{what or command[0]} failed (exit {done.returncode}): {' '.join(command)}\n{output[-4000:]}")
    return output


@contextlib.contextmanager
def _progress(log, what: str):
    """Log "still <what> ... 1m30s elapsed" every KUBEROS_PROGRESS_INTERVAL seconds (30) while the block runs."""
    interval = float(os.environ.get("KUBEROS_PROGRESS_INTERVAL") or 30)
    started, stop = time.monotonic(), threading.Event()

    def tick() -> None:
        while not stop.wait(interval):
            elapsed = int(time.monotonic() - started)
            log(f"local images:   still {what} ... {elapsed // 60}m{elapsed % 60:02d}s elapsed")

    ticker = threading.Thread(target=tick, name=f"progress of {what}", daemon=True)
    ticker.start()
    try:
        yield
    finally:
        stop.set()
        ticker.join()


def _sha256(*parts: str | bytes) -> str:
    digest = hashlib.sha256()
    for part in parts:
        data = part.encode() if isinstance(part, str) else part
        digest.update(len(data).to_bytes(8, "big"))
        digest.update(data)
    return digest.hexdigest()


def _size(path: str) -> int:
    if os.path.isfile(path):
        return os.path.getsize(path)
    total = 0
    for directory, _subdirectories, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(directory, name)).st_size
    return total


def _mib(size: int) -> str:
    return f"{size / 2**20:.1f} MiB"


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _mounts_under(path: str) -> list[str]:
    """Mount points at or below `path`, deepest first (from /proc/self/mountinfo)."""
    path = os.path.realpath(path)
    found = []
    with open("/proc/self/mountinfo", encoding="utf-8") as handle:
        for line in handle:
            point = re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), line.split()[4])  # \040: a space
            if point == path or point.startswith(path + "/"):
                found.append(point)
    return sorted(found, key=len, reverse=True)


def _remove(path: str) -> None:
    """Remove a file or a tree; a tree only after whatever is mounted in it is unmounted (debootstrap mounts
    /proc and /sys in the rootfs while it runs: an interrupted build can leave them, and rmtree must not
    descend into them)."""
    if os.path.isdir(path) and not os.path.islink(path):
        for point in _mounts_under(path):
            subprocess.run(["umount", point], capture_output=True, check=False)
            if point in _mounts_under(path):
                subprocess.run(["umount", "-l", point], capture_output=True, check=False)
        left = _mounts_under(path)
        if left:
            raise ImageBuildError(f"cannot remove {path}: {', '.join(left)} still mounted")
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)


def _require_programs(*programs: str) -> None:
    missing = [program for program in programs if not shutil.which(program)]
    if missing:
        raise ImageBuildError(
            f"building the local images needs {', '.join(missing)} on PATH "
            "(Debian: apt-get install debootstrap umoci gcc libc6-dev)"
        )


def _host_python(repo_root: str) -> str:
    """The Python whose pip installs the wheels: the project venv's (its pip cache, its installed metadata)."""
    python = os.path.join(repo_root, ".venv", "bin", "python")
    return python if os.access(python, os.X_OK) else sys.executable


# --- the base: which distributions ---------------------------------------------------------------------------

_CLOSURE = r"""
import importlib.metadata as md, json, re, sys
try:
    from packaging.requirements import Requirement
except ImportError:
    from pip._vendor.packaging.requirements import Requirement
canon = lambda n: re.sub(r"[-_.]+", "-", n).lower()
versions, missing, stack = {}, [], [(name, "") for name in json.loads(sys.argv[1])]
while stack:
    name, parent = stack.pop()
    if canon(name) in versions:
        continue
    try:
        dist = md.distribution(name)
    except md.PackageNotFoundError:
        versions[canon(name)] = None
        missing.append(f"{name} (needed by {parent or 'the image'})")
        continue
    versions[canon(name)] = dist.version
    for line in dist.requires or []:
        requirement = Requirement(line)
        if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
            stack.append((requirement.name, name))
print(json.dumps({"versions": versions, "missing": missing, "python": "%d.%d" % sys.version_info[:2]}))
"""


def _pins(repo_root: str) -> dict[str, str]:
    """canonical name -> `name==version` line, from the requirements files (the first file that pins a name wins)."""
    pins: dict[str, str] = {}
    for filename in REQUIREMENTS:
        with open(os.path.join(repo_root, filename), encoding="utf-8") as handle:
            for raw in handle:
                line = raw.split("#", 1)[0].strip()
                match = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)\s*==\s*(\S+)", line)
                if match:
                    pins.setdefault(_canonical(match.group(1)), f"{match.group(1)}=={match.group(2)}")
    return pins


def _base_requirements(repo_root: str, python: str, log) -> tuple[list[str], str]:
    """The pinned lines the base installs (sorted), and the Python version of the venv that resolved them."""
    pins = _pins(repo_root)
    roots = list(IMAGE_DISTRIBUTIONS)
    with open(os.path.join(repo_root, INSTALL_ALL_OF), encoding="utf-8") as handle:
        for raw in handle:
            match = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*==", raw)
            if match:
                roots.append(match.group(1))
    output = _run([python, "-c", _CLOSURE, json.dumps(roots)], timeout=120, what="resolving the image's packages")
    report = json.loads(output.strip().splitlines()[-1])  # the last line: warnings may come first
    if report["missing"]:
        raise ImageBuildError(
            f"{python} lacks distributions the image needs: {', '.join(sorted(report['missing']))}; "
            "install the requirements files into the project venv (scripts/setup.sh)"
        )
    lines = []
    for name, version in sorted(report["versions"].items()):
        if name in pins:
            lines.append(pins[name])
        else:  # not pinned anywhere: what the venv has
            log(f"local images: {name} is pinned in no requirements file; using the venv's {version}")
            lines.append(f"{name}=={version}")
    return sorted(lines, key=str.lower), report["python"]


# --- the base: building it -------------------------------------------------------------------------------------


def _chroot(rootfs: str, command: list[str], env: dict[str, str], **kwargs) -> str:
    return _run(["chroot", rootfs, "/usr/bin/env", "-i", *(f"{k}={v}" for k, v in env.items()), *command], **kwargs)


def _fix_shebangs(bin_dir: str) -> int:
    """pip writes the host interpreter into the scripts it generates: point them at the image's."""
    fixed = 0
    for name in sorted(os.listdir(bin_dir)):
        path = os.path.join(bin_dir, name)
        if os.path.islink(path) or not os.path.isfile(path):
            continue
        with open(path, "rb") as handle:
            data = handle.read()
        if not data.startswith(b"#!"):
            continue
        first, newline, rest = data.partition(b"\n")
        if b"python" in first and not first.startswith(f"#!{VENV}/".encode()):
            with open(path, "wb") as handle:
                handle.write(f"#!{VENV}/bin/python3".encode() + newline + rest)
            fixed += 1
    return fixed


def _strip(rootfs: str) -> None:
    """Remove what nothing in the image reads at run time (the copyright files stay)."""
    doc = os.path.join(rootfs, "usr/share/doc")
    for directory, _subdirectories, files in os.walk(doc):
        for name in files:
            if name != "copyright":
                os.unlink(os.path.join(directory, name))
    for relative in ("usr/share/man", "usr/share/info", "usr/share/lintian", "usr/share/linda", f"{VENV[1:]}/include"):
        _remove(os.path.join(rootfs, relative))
    # Test suites of the installed packages (numpy, scipy, ...): nothing imports them at run time.
    for site_packages in glob.glob(os.path.join(rootfs, VENV.lstrip("/"), "lib", "python*", "site-packages")):
        for directory, subdirectories, _files in os.walk(site_packages):
            if "tests" in subdirectories:
                subdirectories.remove("tests")
                _remove(os.path.join(directory, "tests"))
    locale = os.path.join(rootfs, "usr/share/locale")
    if os.path.isdir(locale):
        for name in os.listdir(locale):
            if name != "locale.alias":
                _remove(os.path.join(locale, name))
    for relative, keep in (
        ("var/lib/apt/lists", {"lock", "partial"}),
        ("var/cache/apt", {"archives"}),
        ("var/cache/apt/archives", {"lock", "partial"}),
        ("var/cache/debconf", {"config.dat", "passwords.dat", "templates.dat"}),
        ("var/log", set()),
        ("dev", set()),  # device nodes: the runtime mounts /dev
    ):
        directory = os.path.join(rootfs, relative)
        if os.path.isdir(directory):
            for name in os.listdir(directory):
                if name not in keep:
                    _remove(os.path.join(directory, name))


def _normalise(rootfs: str, since: float) -> None:
    """What makes two builds of the same sources differ, made the same: files written with the build's date or
    host (ldconfig's cache of file times, backups of dpkg's databases, the host's name and resolver, which the
    runtime mounts anyway, what the smoke test left in /tmp), the password-change day in the shadow files, and
    the times of every file written or changed by the build (at or after ``since``) set to SOURCE_DATE, as
    reproducible builds clamp to SOURCE_DATE_EPOCH. Files unpacked from Debian's packages keep their packages' times: Debian's
    byte-compiled standard library records them, and would be recompiled at run time otherwise."""
    for relative in ("var/cache/ldconfig/aux-cache", "etc/hostname", "etc/resolv.conf", "etc/machine-id"):
        _remove(os.path.join(rootfs, relative))
    for relative in ("tmp", "var/tmp"):  # what the smoke test's imports wrote (matplotlib's font cache under HOME=/tmp)
        for name in os.listdir(os.path.join(rootfs, relative)) if os.path.isdir(os.path.join(rootfs, relative)) else ():
            _remove(os.path.join(rootfs, relative, name))
    for path in glob.glob(os.path.join(rootfs, "var/lib/dpkg/*-old")) + glob.glob(os.path.join(rootfs, "etc/*-")):
        _remove(path)
    day = str(APP_MTIME // 86400)
    shadow = os.path.join(rootfs, "etc/shadow")
    if os.path.isfile(shadow):
        with open(shadow, encoding="utf-8") as handle:
            fields = [line.split(":") for line in handle.read().splitlines()]  # name:password:last change (days):...
        text = "\n".join(":".join([*f[:2], day if f[2] else "", *f[3:]] if len(f) > 2 else f) for f in fields)
        mode = os.stat(shadow).st_mode
        with open(shadow, "w", encoding="utf-8") as handle:
            handle.write(text + "\n")
        os.chmod(shadow, mode & 0o7777)
    for directory, subdirectories, files in os.walk(rootfs, topdown=False):
        for name in [*files, *subdirectories, *([""] if directory == rootfs else [])]:
            path = os.path.join(directory, name) if name else directory
            if os.lstat(path).st_mtime >= since:
                os.utime(path, (APP_MTIME, APP_MTIME), follow_symlinks=False)


def _image_environment(rootfs: str) -> dict[str, str]:
    """ros_environment() for the venv in the rootfs, with the paths as the container sees them."""
    env = ros_environment(prefix=os.path.join(rootfs, VENV.lstrip("/")))
    libraries = env["LD_LIBRARY_PATH"].split(os.pathsep)
    if not any(os.path.basename(path).startswith("ros_") for path in libraries):
        raise ImageBuildError(f"no site-packages/ros_*.libs under {rootfs}{VENV}: is this Python's version the image's?")
    for key in ("PATH", "LD_LIBRARY_PATH"):
        env[key] = os.pathsep.join(
            path[len(rootfs) :] if path.startswith(rootfs + "/") else path for path in env[key].split(os.pathsep)
        )
    env.update(
        {
            "ROS_LOG_DIR": "/tmp/ros",
            "HOME": "/tmp",
            "PYTHONPATH": APP_DIR,
            "PYTHONUNBUFFERED": "1",
            "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
            "LANG": "C.UTF-8",
        }
    )
    return env


def _build_base(images: str, key: str, lines: list[str], python: str, python_version: str, log) -> str:
    """Build the base layout into images/base-<key>/ (returns that directory)."""
    _require_programs("debootstrap", "unshare", "chroot", "umoci")
    if os.geteuid() != 0:
        raise ImageBuildError("building the ROS image's base needs root (debootstrap, chroot, root-owned files)")
    started, since = time.monotonic(), time.time()
    work = os.path.join(images, "tmp", f"base-{key}-{os.getpid()}")
    _remove(work)
    os.makedirs(work)
    layout, bundle = os.path.join(work, "layout"), os.path.join(work, "bundle")
    rootfs = os.path.join(bundle, "rootfs")
    _run(["umoci", "init", "--layout", layout])
    _run(["umoci", "new", "--image", f"{layout}:base"])
    _run(["umoci", "unpack", "--image", f"{layout}:base", bundle])

    step = time.monotonic()
    log(f"local images: debootstrap {DEBIAN_SUITE} ({', '.join(DEBIAN_PACKAGES)}) from {DEBIAN_MIRROR}")
    with _progress(log, f"debootstrap {DEBIAN_SUITE}"):
        _run(debootstrap_command(DEBIAN_SUITE, rootfs, DEBIAN_MIRROR, DEBIAN_PACKAGES), what="debootstrap")
    log(f"local images: debootstrap done in {time.monotonic() - step:.0f}s")
    chroot_env = {"PATH": "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin", "LANG": "C.UTF-8", "HOME": "/root"}
    image_python = _chroot(rootfs, ["python3", "-c", "import sys; print('%d.%d' % sys.version_info[:2])"], chroot_env).strip()
    if image_python != python_version:
        raise ImageBuildError(f"{DEBIAN_SUITE}'s python3 is {image_python}, the wheels are for {python}'s {python_version}")
    _chroot(rootfs, ["python3", "-m", "venv", "--without-pip", VENV], chroot_env, what="python3 -m venv in the rootfs")

    step = time.monotonic()
    prefix = os.path.join(rootfs, VENV.lstrip("/"))
    requirements = os.path.join(work, "requirements.txt")
    with open(requirements, "w", encoding="utf-8") as handle:
        handle.write("\n".join(lines) + "\n")
    log(f"local images: pip install {len(lines)} pinned distributions into {VENV}")
    with _progress(log, f"installing {len(lines)} distributions into {VENV}"):
        _run(
            [
                python, "-m", "pip", "install", "--quiet", "--no-deps", "--ignore-installed", "--no-compile",
                "--no-warn-script-location", "--disable-pip-version-check", "--prefix", prefix, "-r", requirements,
            ],
            what="pip install into the image",
        )  # fmt: skip
    fixed = _fix_shebangs(os.path.join(prefix, "bin"))
    log(f"local images: pip done in {time.monotonic() - step:.0f}s ({fixed} scripts pointed at {VENV}/bin/python3)")

    _strip(rootfs)
    step = time.monotonic()
    site_packages = os.path.join(prefix, "lib", f"python{python_version}", "site-packages")
    # The venv's Python compiles for the image's (the same minor version: the same bytecode); -s/-p record the
    # image's paths. Unchecked-hash pycs: the layer's tar rounds mtimes to the second (timestamp pycs would be
    # stale for half the files), and the image's sources never change. Test directories are not imported.
    compile_options = ["-q", "-j", "0", "--invalidation-mode", "unchecked-hash", "-x", r"/tests?/", "-s", rootfs, "-p", "/"]
    with _progress(log, "byte-compiling the venv"):
        _run([python, "-m", "compileall", *compile_options, site_packages], what="byte-compiling the venv")
    log(f"local images: byte-compiled in {time.monotonic() - step:.0f}s")

    env = _image_environment(rootfs)
    _chroot(rootfs, [f"{VENV}/bin/python3", "-c", f"import {', '.join(SMOKE_IMPORTS)}"], env, what="importing in the rootfs")
    log(f"local images: rootfs is {_mib(_size(rootfs))}; packing it (umoci repack)")

    step = time.monotonic()
    with _progress(log, "packing the rootfs"):
        _normalise(rootfs, since - 1)
        history = ("--history.created_by", f"kuberos local_images base {key}")
        _run(["umoci", "repack", "--image", f"{layout}:base", *CREATED, *history, bundle])
    config = ["umoci", "config", "--image", f"{layout}:base", "--created", SOURCE_DATE, *CREATED, "--config.workingdir"]
    config.append(APP_DIR)
    for name, value in env.items():
        config += ["--config.env", f"{name}={value}"]
    _run([*config, "--history.created_by", "kuberos local_images environment"])
    _remove(bundle)
    log(f"local images: packed in {time.monotonic() - step:.0f}s")

    info = {
        "key": key,
        "requirements": lines,
        "suite": DEBIAN_SUITE,
        "environment": env,
        "build_seconds": round(time.monotonic() - started, 1),
        "layout_bytes": _size(layout),
    }
    with open(os.path.join(work, "info.json"), "w", encoding="utf-8") as handle:
        json.dump(info, handle, indent=1)
    final = os.path.join(images, f"base-{key}")
    _remove(final)
    os.rename(work, final)
    log(f"local images: base {key} built in {info['build_seconds']:.0f}s ({_mib(info['layout_bytes'])} compressed)")
    return final


# --- the application layer and the archives ------------------------------------------------------------------


def _app_files(repo_root: str) -> list[tuple[str, bytes | None, bool]]:
    """(path in the image without the leading /, content or None for a directory, executable), sorted by path.

    Read once: the key and the layer come from the same bytes, even while someone edits the files."""
    entries: dict[str, tuple[bytes | None, bool]] = {}
    for source, destination in APP_TREES:
        top = os.path.join(repo_root, source)
        if not os.path.isdir(top):
            raise ImageBuildError(
                f"{top} is missing: the lab builds its images from a checkout of the collection's repository"
                " (the installed collection leaves sim/ out)"
            )
        parts = destination.strip("/").split("/")
        for depth in range(1, len(parts)):
            entries.setdefault("/".join(parts[:depth]), (None, True))
        for directory, subdirectories, files in os.walk(top):
            subdirectories[:] = sorted(d for d in subdirectories if d != "__pycache__" and not d.startswith("."))
            relative = os.path.relpath(directory, top)
            target = destination.strip("/") if relative == "." else f"{destination.strip('/')}/{relative}"
            entries[target] = (None, True)
            for name in files:
                path = os.path.join(directory, name)
                if name.endswith((".pyc", ".pyo")) or name.startswith(".") or not os.path.isfile(path):
                    continue
                with open(path, "rb") as handle:
                    entries[f"{target}/{name}"] = (handle.read(), bool(os.stat(path).st_mode & 0o111))
    return [(target, *entries[target]) for target in sorted(entries)]


def _app_key(files: list[tuple[str, bytes | None, bool]]) -> str:
    parts: list[str | bytes] = [RECIPE_VERSION]
    for target, content, executable in files:
        parts += [f"{target}/"] if content is None else [target, str(executable), content]
    return _sha256(*parts)


def _write_app_layer(files: list[tuple[str, bytes | None, bool]], path: str) -> None:
    with tarfile.open(path, "w", format=tarfile.PAX_FORMAT) as tar:
        for target, content, executable in files:
            info = tarfile.TarInfo(target)
            info.uid = info.gid = 0
            info.uname = info.gname = "root"
            info.mtime = APP_MTIME
            info.mode = 0o755 if executable else 0o644
            if content is None:
                info.type = tarfile.DIRTYPE
                tar.addfile(info)
            else:
                info.size = len(content)
                tar.addfile(info, io.BytesIO(content))


def _descriptor(layout: str, tag: str) -> dict:
    with open(os.path.join(layout, "index.json"), encoding="utf-8") as handle:
        index = json.load(handle)
    for descriptor in index["manifests"]:
        if descriptor.get("annotations", {}).get(REF_ANNOTATION) == tag:
            return descriptor
    raise ImageBuildError(f"{layout} has no image tagged {tag}")


def _blob(layout: str, digest: str) -> str:
    algorithm, _sep, hexdigest = digest.partition(":")
    return os.path.join(layout, "blobs", algorithm, hexdigest)


def _write_archive(layout: str, tag: str, reference: str, destination: str) -> None:
    """The image `tag` of an OCI layout as an OCI archive named `reference`: written in tmp/ next to
    `destination`, renamed to it when complete."""
    descriptor = dict(_descriptor(layout, tag))
    with open(_blob(layout, descriptor["digest"]), encoding="utf-8") as handle:
        manifest = json.load(handle)
    digests = [descriptor["digest"], manifest["config"]["digest"], *(layer["digest"] for layer in manifest["layers"])]
    descriptor["annotations"] = {REF_ANNOTATION: reference.rpartition(":")[2], NAME_ANNOTATION: reference}
    index = json.dumps({"schemaVersion": 2, "manifests": [descriptor]}, indent=1).encode()
    temporary = os.path.join(os.path.dirname(destination), "tmp", f"{os.path.basename(destination)}.{os.getpid()}")
    try:
        with tarfile.open(temporary, "w", format=tarfile.PAX_FORMAT) as tar:

            def add(name: str, data: bytes | None = None, path: str | None = None) -> None:
                info = tarfile.TarInfo(name)
                info.mtime = APP_MTIME
                if data is None and path is None:
                    info.type, info.mode = tarfile.DIRTYPE, 0o755
                    tar.addfile(info)
                elif data is not None:
                    info.size, info.mode = len(data), 0o644
                    tar.addfile(info, io.BytesIO(data))
                else:
                    info.size, info.mode = os.path.getsize(path), 0o644
                    with open(path, "rb") as handle:
                        tar.addfile(info, handle)

            add("oci-layout", b'{"imageLayoutVersion":"1.0.0"}')
            add("index.json", index)
            add("blobs/")
            add("blobs/sha256/")
            for digest in dict.fromkeys(digests):
                add(f"blobs/{digest.replace(':', '/')}", path=_blob(layout, digest))
        os.replace(temporary, destination)
    finally:
        _remove(temporary)


def _copy_layout(source: str, destination: str) -> None:
    """A layout to append to: blobs hard-linked (they never change), index.json and oci-layout copied."""
    os.makedirs(os.path.join(destination, "blobs", "sha256"))
    for name in ("index.json", "oci-layout"):
        shutil.copyfile(os.path.join(source, name), os.path.join(destination, name))
    blobs = os.path.join(source, "blobs", "sha256")
    for name in os.listdir(blobs):
        target = os.path.join(destination, "blobs", "sha256", name)
        try:
            os.link(os.path.join(blobs, name), target)
        except OSError:
            shutil.copyfile(os.path.join(blobs, name), target)


def _build_on_base(images: str, base: str, key: str, files, reference: str, archive: str, what: str, config=()) -> None:
    """The base plus one layer of ``files`` (as _app_files returns them) and ``umoci config`` options, as the OCI
    archive of ``reference``: built in tmp/, renamed into place when complete."""
    work = os.path.join(images, "tmp", f"{reference.split('/')[-1].replace(':', '-')}-{os.getpid()}")
    _remove(work)
    os.makedirs(work)
    try:
        layout = os.path.join(work, "layout")
        _copy_layout(os.path.join(base, "layout"), layout)
        layer = os.path.join(work, "layer.tar")
        _write_app_layer(files, layer)
        _run(
            ["umoci", "raw", "add-layer", "--image", f"{layout}:base", "--tag", key, *CREATED,
             "--history.created_by", f"kuberos local_images {what}", layer],
        )  # fmt: skip
        if config:
            _run(["umoci", "config", "--image", f"{layout}:{key}", *config, *CREATED, "--history.created_by", f"kuberos {what}"])
        _write_archive(layout, key, reference, archive)
    finally:
        _remove(work)


def _setup_script(environment: dict[str, str]) -> str:
    """``/opt/ros/<distro>/setup.bash`` of the published-layout image: what a ROS installation's setup exports
    (the wheels' bin and library directories, the distribution), for bash and sh alike."""
    lines = [
        f"# ROS 2 {ROS_DISTRO} from PyPI wheels under {VENV} (kuberos local_images: the published ROS image's layout)",
        f'export PATH="{VENV}/bin${{PATH:+:$PATH}}"',
        f'export LD_LIBRARY_PATH="{environment["LD_LIBRARY_PATH"]}${{LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}}"',
        f"export AMENT_PREFIX_PATH={VENV}",
        f"export ROS_DISTRO={ROS_DISTRO}",
        "export ROS_VERSION=2",
        "export ROS_PYTHON_VERSION=3",
        "export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1",
        "",
    ]
    return "\n".join(lines)


ENTRYPOINT_SCRIPT = """#!/bin/bash
set -e

# setup ros2 environment
source "/opt/ros/$ROS_DISTRO/setup.bash" --
exec "$@"
"""

# The published image's configuration: no ROS on PATH, the distribution named, bash by default.
ROS_BASE_ENV = (
    "PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
    "LANG=C.UTF-8",
    "LC_ALL=C.UTF-8",
    f"ROS_DISTRO={ROS_DISTRO}",
)


def _ros_base_files(base: str) -> list[tuple[str, bytes | None, bool]]:
    """The published-layout image's own layer: the entrypoint and the setup scripts (as _app_files returns)."""
    with open(os.path.join(base, "info.json"), encoding="utf-8") as handle:
        setup = _setup_script(json.load(handle)["environment"]).encode()
    prefix = VENV.strip("/")
    return [
        (ROS_ENTRYPOINT.strip("/"), ENTRYPOINT_SCRIPT.encode(), True),
        (f"{prefix}/local_setup.bash", setup, False),
        (f"{prefix}/setup.bash", setup, False),
        (f"{prefix}/setup.sh", setup, False),
    ]


def _prometheus_files() -> list[tuple[str, bytes | None, bool]]:
    """The Prometheus image's own layer (as _app_files returns): the program, a default configuration, and the
    empty directory ``/prometheus`` that the pod mounts its storage volume on."""
    try:
        with open(PROMETHEUS_BINARY, "rb") as handle:
            program = handle.read()
    except OSError as error:
        raise ImageBuildError(
            f"{PROMETHEUS_BINARY}: {error.strerror}; Debian's prometheus package is not installed (scripts/setup.sh installs it)"
        ) from None
    return [
        ("bin/prometheus", program, True),
        ("etc/prometheus", None, True),
        ("etc/prometheus/prometheus.yml", PROMETHEUS_CONFIG.encode(), False),
        ("prometheus", None, True),
    ]


def _build_pause(repo_root: str, images: str, key: str, archive: str) -> None:
    _require_programs("gcc", "umoci")
    work = os.path.join(images, "tmp", f"pause-{key}-{os.getpid()}")
    _remove(work)
    os.makedirs(work)
    try:
        layout, bundle = os.path.join(work, "layout"), os.path.join(work, "bundle")
        _run(["umoci", "init", "--layout", layout])
        _run(["umoci", "new", "--image", f"{layout}:pause"])
        _run(["umoci", "unpack", "--image", f"{layout}:pause", bundle])
        program = os.path.join(bundle, "rootfs", "pause")
        _run(["gcc", "-static", "-Os", "-s", "-Wall", "-o", program, os.path.join(repo_root, PAUSE_SOURCE)], what="gcc")
        os.chmod(program, 0o755)
        _normalise(os.path.join(bundle, "rootfs"), 0)
        history = ("--history.created_by", f"gcc -static -Os {PAUSE_SOURCE}")
        _run(["umoci", "repack", "--image", f"{layout}:pause", *CREATED, *history, bundle])
        _run(["umoci", "config", "--image", f"{layout}:pause", "--created", SOURCE_DATE, "--config.entrypoint", "/pause",
              "--no-history"])  # fmt: skip
        _write_archive(layout, "pause", PAUSE_IMAGE, archive)
    finally:
        _remove(work)


def _prune(images: str, pattern: str, keep: int, current: str, log) -> None:
    """Remove all but the newest `keep` entries matching `pattern` (the current one always stays)."""
    entries = [os.path.join(images, name) for name in os.listdir(images) if re.fullmatch(pattern, name)]
    entries.sort(key=lambda path: os.stat(path).st_mtime, reverse=True)
    kept = [current]
    for path in entries:
        if path == current:
            continue
        if len(kept) < keep:
            kept.append(path)
        else:
            log(f"local images: removing the old {os.path.basename(path)}")
            _remove(path)


@contextlib.contextmanager
def _locked(images: str, log):
    with open(os.path.join(images, ".lock"), "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno not in (errno.EAGAIN, errno.EACCES):
                raise
            log(f"local images: waiting for another build ({images}/.lock)")
            fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _build(repo_root: str, cache_dir: str, log=print) -> list[dict]:
    """Build or reuse the four images; one dict per image: reference, archive, bytes, seconds, cached."""
    repo_root, cache_dir = os.path.realpath(repo_root), os.path.abspath(os.path.expanduser(cache_dir))
    images = os.path.join(cache_dir, "images")
    os.makedirs(images, exist_ok=True)
    results = []
    with _locked(images, log):
        # Under the lock nothing else builds: whatever is in tmp/ is left from an interrupted build.
        _remove(os.path.join(images, "tmp"))
        os.makedirs(os.path.join(images, "tmp"))

        results.append(_pause(repo_root, images, log))

        started = time.monotonic()
        python = _host_python(repo_root)
        lines, python_version = _base_requirements(repo_root, python, log)
        base_key = _sha256(RECIPE_VERSION, DEBIAN_SUITE, *DEBIAN_PACKAGES, python_version, *lines)[:12]
        base = os.path.join(images, f"base-{base_key}")
        if os.path.exists(os.path.join(base, "info.json")):
            os.utime(base)

        def on_base(key: str, files, reference: str, what: str, config=()):
            def build(archive: str) -> None:
                built = _ensure_base(images, base, base_key, lines, python, python_version, log)
                _build_on_base(images, built, key, files(built), reference, archive, what, config)

            return build

        files = _app_files(repo_root)
        key = _sha256(base_key, _app_key(files), *APP_IMAGE_CONFIG)[:12]
        build_ros = on_base(key, lambda _base: files, f"{ROS_IMAGE}:{key}", f"application {key}", APP_IMAGE_CONFIG)
        results.append(_archive(images, "ros", key, f"{ROS_IMAGE}:{key}", build_ros, started, log))

        started = time.monotonic()
        key = _sha256(RECIPE_VERSION, base_key, ENTRYPOINT_SCRIPT, *ROS_BASE_ENV, _setup_script({"LD_LIBRARY_PATH": ""}))[:12]
        config = ["--clear=config.env", "--config.workingdir", "/"]
        config += [option for item in ROS_BASE_ENV for option in ("--config.env", item)]
        config += ["--config.entrypoint", ROS_ENTRYPOINT, "--config.cmd", "bash"]
        what = f"{ROS_ENTRYPOINT}, setup scripts, ENTRYPOINT (the published ROS image's layout)"
        build_ros_base = on_base(key, _ros_base_files, f"{ROS_BASE_IMAGE}:{key}", what, config)
        results.append(_archive(images, "ros-base", key, f"{ROS_BASE_IMAGE}:{key}", build_ros_base, started, log))

        started = time.monotonic()
        prometheus = _prometheus_files()
        key = _sha256(base_key, _app_key(prometheus), *PROMETHEUS_IMAGE_CONFIG)[:12]
        what = "Debian's /usr/bin/prometheus, ENTRYPOINT (as prom/prometheus runs it)"
        build_prometheus = on_base(key, lambda _base: prometheus, f"{PROMETHEUS_IMAGE}:{key}", what, PROMETHEUS_IMAGE_CONFIG)
        results.append(_archive(images, "prometheus", key, f"{PROMETHEUS_IMAGE}:{key}", build_prometheus, started, log))
    return results


def _pause(repo_root: str, images: str, log) -> dict:
    """The pause image's archive, built unless cached (the caller holds the lock)."""
    started = time.monotonic()
    with open(os.path.join(repo_root, PAUSE_SOURCE), "rb") as handle:
        pause_key = _sha256(RECIPE_VERSION, handle.read())[:12]
    build_pause = functools.partial(_build_pause, repo_root, images, pause_key)
    return _archive(images, "pause", pause_key, PAUSE_IMAGE, build_pause, started, log)


def build_pause(repo_root: str, cache_dir: str, log=print) -> str:
    """Only the pause image (seconds, no Debian base): its OCI archive."""
    images = os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "images")
    os.makedirs(os.path.join(images, "tmp"), exist_ok=True)
    with _locked(images, log):
        return _pause(os.path.realpath(repo_root), images, log)["archive"]


def _archive(images: str, kind: str, key: str, reference: str, build, started: float, log) -> dict:
    """The archive ``<kind>-<key>.tar``: reused when it exists (touched: the newest archives are the ones in use,
    which _prune keeps), else built by ``build(archive)`` and the older ones of its kind pruned."""
    archive = os.path.join(images, f"{kind}-{key}.tar")
    cached = os.path.exists(archive)
    if cached:
        os.utime(archive)
    else:
        build(archive)
        _prune(images, rf"{re.escape(kind)}-[0-9a-f]{{12}}\.tar", KEEP_ARCHIVES, archive, log)
    return _result(reference, archive, started, cached)


def _ensure_base(images: str, base: str, base_key: str, lines: list[str], python: str, python_version: str, log) -> str:
    if not os.path.exists(os.path.join(base, "info.json")):
        base = _build_base(images, base_key, lines, python, python_version, log)
    _prune(images, r"base-[0-9a-f]{12}", KEEP_BASES, base, log)
    return base


def _result(reference: str, archive: str, started: float, cached: bool) -> dict:
    return {
        "reference": reference,
        "archive": archive,
        "bytes": os.path.getsize(archive),
        "seconds": round(time.monotonic() - started, 1),
        "cached": cached,
    }


def build_images(repo_root: str, cache_dir: str, log=print) -> dict[str, str]:
    """Build (or reuse from `<cache_dir>/images/`) the pause, ROS, published-layout ROS and Prometheus images:
    {image reference: OCI archive path}."""
    results = _build(repo_root, cache_dir, log)
    for result in results:
        how = "cached" if result["cached"] else f"built in {result['seconds']:.1f}s"
        log(f"local images: {result['reference']} {how}: {result['archive']} ({_mib(result['bytes'])})")
    return {result["reference"]: result["archive"] for result in results}


def _qualified(reference: str) -> str:
    """The full name containerd stores (the Docker Hub defaults spelled out)."""
    name, _sep, digest = reference.partition("@")
    first = name.split("/", 1)[0]
    if "/" not in name or ("." not in first and ":" not in first and first != "localhost"):
        name = f"docker.io/{name}" if "/" in name else f"docker.io/library/{name}"
    last = name.rsplit("/", 1)[-1]
    if not digest and ":" not in last:
        name += ":latest"
    return f"{name}@{digest}" if digest else name


def image_aliases(images) -> dict[str, str]:
    """The names under which containerd must also know the built images (`images`: their references, as
    build_images returns them): {alias: reference}, fully qualified. The project's ROS image serves the modules,
    the bridge and the controller; the published-layout image serves the discovery servers' default image."""
    aliases = {}
    for reference in images:
        if reference.startswith(f"{ROS_IMAGE}:"):
            aliases.update({_qualified(alias): _qualified(reference) for alias in ALIASES})
        elif reference.startswith(f"{ROS_BASE_IMAGE}:"):
            aliases.update({_qualified(alias): _qualified(reference) for alias in ROS_BASE_ALIASES})
        elif reference.startswith(f"{PROMETHEUS_IMAGE}:"):
            aliases.update({_qualified(alias): _qualified(reference) for alias in PROMETHEUS_ALIASES})
    return aliases


# --- importing -------------------------------------------------------------------------------------------------


def archive_image(archive: str) -> tuple[str, str]:
    """The (name, manifest digest) of the one image in an archive written by build_images."""
    with tarfile.open(archive, "r:") as tar:
        for member in tar:
            if member.name in ("index.json", "./index.json"):
                index = json.load(tar.extractfile(member))
                break
        else:
            raise ImageBuildError(f"{archive} has no index.json: not an OCI archive")
    (descriptor,) = index["manifests"]
    annotations = descriptor.get("annotations", {})
    return annotations.get(NAME_ANNOTATION) or annotations[REF_ANNOTATION], descriptor["digest"]


def _images(command: list[str], snapshotter: str) -> dict[str, dict]:
    """ref -> {digest, unpacked, labels} in the namespace."""
    state: dict[str, dict] = {}
    for line in _run([*command, "images", "check", "--snapshotter", snapshotter], timeout=120).splitlines()[1:]:
        parts = line.split()
        if len(parts) >= 6:
            state[parts[0]] = {"digest": parts[2], "unpacked": parts[-1] == "true", "labels": set()}
    for line in _run([*command, "images", "ls"], timeout=120).splitlines()[1:]:
        parts = line.split()
        if len(parts) >= 6 and parts[0] in state:
            state[parts[0]]["labels"] = set(parts[-1].split(","))
    return state


def import_images(
    ctr: str,
    address: str,
    archives: dict[str, str],
    aliases: dict[str, str],
    namespace: str = "k8s.io",
    log=print,
    *,
    snapshotter: str = "overlayfs",
) -> list[str]:
    """Import the archives into the containerd at `address`, tag the aliases, pin all of them; what was done.

    Images already there with the archive's digest and unpacked for `snapshotter` are not imported again,
    aliases that already point at their image's digest are not tagged again: a repeated call returns [].
    """
    command = [ctr, "-a", address, "-n", namespace]
    state = _images(command, snapshotter)
    done: list[str] = []
    digests: dict[str, str] = {}
    for reference, archive in archives.items():
        reference = _qualified(reference)
        name, digest = archive_image(archive)
        digests[reference] = digest
        current = state.get(reference)
        if current and current["digest"] == digest and current["unpacked"]:
            continue
        started = time.monotonic()
        with _progress(log, f"importing {reference} into {address}"):
            _run([*command, "images", "import", "--snapshotter", snapshotter, archive], what="ctr images import")
        if _qualified(name) != reference:
            _run([*command, "images", "tag", "--force", _qualified(name), reference], what="ctr images tag")
        done.append(f"imported {reference} ({digest}) from {archive} in {time.monotonic() - started:.1f}s")
        log(f"local images: {done[-1]}")
    if done:
        state = _images(command, snapshotter)
    for alias, source in aliases.items():
        alias, source = _qualified(alias), _qualified(source)
        digest = digests.get(source) or state.get(source, {}).get("digest")
        if digest is None:
            raise ImageBuildError(f"cannot tag {alias}: {source} is not in containerd's {namespace} namespace")
        if state.get(alias, {}).get("digest") == digest:
            continue
        _run([*command, "images", "tag", "--force", source, alias], what="ctr images tag")
        done.append(f"tagged {alias} -> {source}")
        log(f"local images: {done[-1]}")
    if done:
        state = _images(command, snapshotter)
    for reference in dict.fromkeys([*map(_qualified, archives), *map(_qualified, aliases)]):
        if PIN_LABEL not in state.get(reference, {}).get("labels", set()):
            _run([*command, "images", "label", reference, PIN_LABEL], what="ctr images label")
            done.append(f"pinned {reference}")
    return done


# --- command line ----------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--repo-root", default=os.path.dirname(os.path.dirname(os.path.dirname(here))), help="the repository [%(default)s]"
    )
    common.add_argument(
        "--cache-dir",
        default=os.environ.get("KUBEROS_CACHE_DIR") or os.path.expanduser("~/.cache/kuberos"),
        help="cache root; images go to <cache-dir>/images [%(default)s]",
    )
    common.add_argument(
        "--json", action="store_true", help='print {"images": {reference: archive}, "aliases": {alias: reference}, ...}'
    )
    parser = argparse.ArgumentParser(
        prog="python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_images",
        description="Build the collection's container images as OCI archives (cached), or import them into a containerd.",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("build", parents=[common], help="build (or reuse) the images; print reference, archive, size, build time")
    imports = commands.add_parser("import", parents=[common], help="build, then import into a containerd and tag the aliases")
    imports.add_argument("--address", required=True, help="containerd socket")
    imports.add_argument("--ctr", default="ctr", help="ctr program [%(default)s]")
    imports.add_argument("--namespace", default="k8s.io", help="containerd namespace [%(default)s]")
    args = parser.parse_args(argv)

    def progress(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    try:
        results = _build(args.repo_root, args.cache_dir, log=progress)
        archives = {result["reference"]: result["archive"] for result in results}
        aliases = image_aliases(archives)
        done = None
        if args.command == "import":
            done = import_images(args.ctr, args.address, archives, aliases, args.namespace, log=progress)
    except ImageBuildError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    if args.json:
        report = {"images": archives, "aliases": aliases, "builds": results}
        if done is not None:
            report["imported"] = done
        print(json.dumps(report, indent=1))
        return 0
    for result in results:
        how = "cached" if result["cached"] else "built"
        print(f"{result['reference']}\t{result['archive']}\t{_mib(result['bytes'])}\t{how} in {result['seconds']:.1f}s")
    for line in done or []:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
