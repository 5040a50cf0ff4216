"""The local container images (plugins/module_utils/kuberos_lab/local_images.py), built for real and run in a private containerd.

The images are built into the real cache (``$KUBEROS_CACHE_DIR`` or ``~/.cache/kuberos``): the first run
builds the ROS image's base (debootstrap and the wheels: a few minutes), later runs reuse it and take about a
minute, most of it containerd unpacking the ROS image. A containerd of this module's own (its root, state,
socket and runc root in a temporary directory; the CRI plugin on, as on the real nodes) imports them; the
teardown stops its containers, shims and the daemon, and unmounts everything under its directory.

Checks: a second build is a cache hit; a changed source file rebuilds only the top layer; importing twice
imports nothing the second time; every alias names the ROS image's digest (and the CRI sees it); the ROS image
runs the pick-and-place modules' imports and rclpy without recompiling a single .pyc, fast-discovery-server
from PATH, and the controller and bridge entry points as the controller's pod runs them (uid 65532, read-only
root filesystem); the pause process exits 0 on SIGTERM.

Needs root, debootstrap, chroot, umoci, gcc (with libc6-dev: a static libc), containerd, ctr and runc (skipped
otherwise; failed when CI is set, as scripts/setup.sh installs them).
"""

from __future__ import annotations

import contextlib
import gzip
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import tarfile
import time

import pytest
from helpers import ROOT

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images

# No `integration` marker exists; the images are the real-node tier's (pyproject.toml: "pods from locally built images").
pytestmark = pytest.mark.real_nodes

TOOLS = ("debootstrap", "chroot", "umoci", "gcc", "containerd", "ctr", "runc")
CACHE_DIR = os.environ.get("KUBEROS_CACHE_DIR") or os.path.expanduser("~/.cache/kuberos")
START_TIMEOUT = 30.0
RUN_TIMEOUT = 180.0

CONTAINERD_CONFIG = """\
version = 2
root = "{root}"
state = "{state}"

[grpc]
  address = "{address}"

[plugins."io.containerd.internal.v1.opt"]
  path = "{opt}"

[plugins."io.containerd.grpc.v1.cri"]
  restrict_oom_score_adj = true

[plugins."io.containerd.grpc.v1.cri".containerd.runtimes.runc.options]
  SystemdCgroup = false
"""

MODULE_IMPORTS = """
import sys
import rclpy, std_msgs.msg, pybullet, ompl, toppra, kuberos_pnp.planner
rclpy.init()
node = rclpy.create_node("kuberos_image_check")
node.destroy_node()
rclpy.shutdown()
print("executable", sys.executable)
"""

ENTRY_IMPORTS = """
import sys
import ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.cli
import ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.core
import ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.ros_side
import kubernetes.client, grpc, cryptography, yaml, jsonschema
import aiohttp.web, prometheus_client  # the controller's dashboard and /metrics
print("prefix", sys.prefix)
"""


# --- fixtures -------------------------------------------------------------------------------------------------


def require_tools() -> None:
    """Skip without root or a program; on CI (CI set: scripts/setup.sh installs them all) fail instead."""
    problem = None
    if os.geteuid() != 0:
        problem = "building and running the local images needs root (debootstrap, chroot, containerd)"
    elif missing := [tool for tool in TOOLS if not shutil.which(tool)]:
        problem = f"missing {', '.join(missing)} (Debian: apt-get install debootstrap umoci gcc libc6-dev containerd runc)"
    if problem and os.environ.get("CI"):
        pytest.fail(problem)
    if problem:
        pytest.skip(problem)


@pytest.fixture(scope="module")
def built() -> dict[str, str]:
    require_tools()
    return local_images.build_images(ROOT, CACHE_DIR)


@pytest.fixture(scope="module")
def ros_image(built) -> str:
    (reference,) = [reference for reference in built if reference.startswith(f"{local_images.ROS_IMAGE}:")]
    return reference


@pytest.fixture(scope="module")
def ros_base_image(built) -> str:
    (reference,) = [reference for reference in built if reference.startswith(f"{local_images.ROS_BASE_IMAGE}:")]
    return reference


class Containerd:
    """A containerd of the test's own: everything under `directory`, socket `address`."""

    def __init__(self, directory: str):
        self.directory = directory
        self.address = os.path.join(directory, "containerd.sock")
        self.runc_root = os.path.join(directory, "runc")
        self.log = os.path.join(directory, "containerd.log")
        self.config = os.path.join(directory, "config.toml")
        with open(self.config, "w", encoding="utf-8") as handle:
            handle.write(
                CONTAINERD_CONFIG.format(
                    root=os.path.join(directory, "root"),
                    state=os.path.join(directory, "state"),
                    address=self.address,
                    opt=os.path.join(directory, "opt"),
                )
            )
        self.process: subprocess.Popen | None = None

    @property
    def ctr(self) -> list[str]:
        return ["ctr", "-a", self.address, "-n", "k8s.io"]

    def start(self) -> None:
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen(
                ["containerd", "--config", self.config], stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                start_new_session=True,
            )  # fmt: skip
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                break
            if subprocess.run(["ctr", "-a", self.address, "version"], capture_output=True, timeout=10).returncode == 0:
                return
            time.sleep(0.2)
        pytest.fail(f"containerd did not start:\n{self.tail()}")

    def tail(self) -> str:
        with open(self.log, encoding="utf-8", errors="replace") as handle:
            return handle.read()[-3000:]

    def run(self, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run([*self.ctr, *args], capture_output=True, text=True, timeout=timeout)

    def container(self, image: str, *command: str, options: tuple[str, ...] = ()) -> tuple[str, list[str]]:
        """A `ctr run --rm` command line (runc with this containerd's own root) and the container's id."""
        name = f"kuberos-image-test-{secrets.token_hex(4)}"
        return name, [*self.ctr, "run", "--rm", "--runc-root", self.runc_root, *options, image, name, *command]

    def images(self) -> dict[str, tuple[str, str]]:
        """ref -> (digest, labels)."""
        listing = self.run("images", "ls").stdout.splitlines()[1:]
        return {parts[0]: (parts[2], parts[-1]) for parts in map(str.split, listing) if len(parts) >= 6}

    def shims(self) -> list[int]:
        """The shims this containerd started (they carry its address on their command line)."""
        found = []
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    with open(f"/proc/{entry}/cmdline", "rb") as handle:
                        argv = handle.read().split(b"\0")
                except OSError:
                    continue
                if argv and b"containerd-shim" in argv[0] and self.address.encode() in argv:
                    found.append(int(entry))
        return found

    def stop(self) -> None:
        if self.process and self.process.poll() is None:
            for namespace in self.run("namespaces", "ls", "-q").stdout.split():
                ctr = ["ctr", "-a", self.address, "-n", namespace]
                for task in subprocess.run([*ctr, "tasks", "ls", "-q"], capture_output=True, text=True).stdout.split():
                    subprocess.run([*ctr, "tasks", "kill", "-s", "SIGKILL", task], capture_output=True, check=False)
                    subprocess.run([*ctr, "tasks", "rm", "-f", task], capture_output=True, check=False)
                for container in subprocess.run([*ctr, "containers", "ls", "-q"], capture_output=True, text=True).stdout.split():
                    subprocess.run([*ctr, "containers", "rm", container], capture_output=True, check=False)
        for pid in self.shims():
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if self.process and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=15)
        for point in local_images._mounts_under(self.directory):
            if subprocess.run(["umount", point], capture_output=True).returncode != 0:
                subprocess.run(["umount", "-l", point], capture_output=True, check=False)
        if not local_images._mounts_under(self.directory):
            shutil.rmtree(self.directory, ignore_errors=True)


@pytest.fixture(scope="module")
def containerd(built, tmp_path_factory):
    # A short path: the socket's must fit in sun_path (108 bytes).
    daemon = Containerd(str(tmp_path_factory.mktemp("ctd")))
    try:
        daemon.start()
        yield daemon
    finally:
        daemon.stop()


@pytest.fixture(scope="module")
def imported(built, ros_image, containerd) -> list[str]:
    return local_images.import_images("ctr", containerd.address, built, local_images.image_aliases(built))


def archive_layers(archive: str) -> tuple[dict, dict, list[list[str]]]:
    """An archive's manifest, config, and the names in each of its layers."""
    with tarfile.open(archive) as tar:
        index = json.load(tar.extractfile("index.json"))

        def blob(digest: str):
            return tar.extractfile(f"blobs/{digest.replace(':', '/')}")

        manifest = json.load(blob(index["manifests"][0]["digest"]))
        config = json.load(blob(manifest["config"]["digest"]))
        layers = []
        for layer in manifest["layers"]:
            if len(manifest["layers"]) > 1 and layer is manifest["layers"][0]:
                layers.append([])  # the base: not listed (a gigabyte to decompress)
                continue
            with tarfile.open(fileobj=gzip.GzipFile(fileobj=blob(layer["digest"]))) as files:
                layers.append(files.getnames())
    return manifest, config, layers


# --- building -------------------------------------------------------------------------------------------------


def test_image_aliases_are_fully_qualified():
    aliases = local_images.image_aliases(
        ["kuberos.local/pause:3.10", "kuberos.local/ros:0123456789ab", "kuberos.local/ros-base:ba5e0123abcd"]
    )
    assert aliases == {
        "ghcr.io/kuberos/pnp-perception:0.1": "kuberos.local/ros:0123456789ab",
        "ghcr.io/kuberos/pnp-planner:0.1": "kuberos.local/ros:0123456789ab",
        "ghcr.io/kuberos/pnp-control:0.1": "kuberos.local/ros:0123456789ab",
        "ghcr.io/kuberos/pnp-coordinator:0.1": "kuberos.local/ros:0123456789ab",
        "ghcr.io/kuberos/pnp-robot-sim:0.1": "kuberos.local/ros:0123456789ab",
        "ghcr.io/kuberos/bridge:0.2.0": "kuberos.local/ros:0123456789ab",
        "ghcr.io/kuberos/controller:0.2.0": "kuberos.local/ros:0123456789ab",
        "docker.io/library/ros:jazzy-ros-base": "kuberos.local/ros-base:ba5e0123abcd",
    }


def test_build_is_cached_and_named(built, ros_image, ros_base_image):
    (prometheus,) = [reference for reference in built if reference.startswith(f"{local_images.PROMETHEUS_IMAGE}:")]
    assert set(built) == {local_images.PAUSE_IMAGE, ros_image, ros_base_image, prometheus}
    assert re.fullmatch(r"kuberos\.local/prometheus:[0-9a-f]{12}", prometheus)
    assert re.fullmatch(r"kuberos\.local/ros:[0-9a-f]{12}", ros_image)
    assert re.fullmatch(r"kuberos\.local/ros-base:[0-9a-f]{12}", ros_base_image)
    started = time.monotonic()
    again = local_images.build_images(ROOT, CACHE_DIR, log=lambda message: None)
    assert again == built
    assert time.monotonic() - started < 15, "a second build with nothing changed must reuse the archives"
    for reference, archive in built.items():
        assert os.path.isfile(archive)
        assert local_images.archive_image(archive)[0] == reference
    assert os.listdir(os.path.join(CACHE_DIR, "images", "tmp")) == [], "a finished build leaves nothing in tmp/"


def test_prometheus_image_runs_debians_program_as_the_published_image_does(built):
    """Debian's /usr/bin/prometheus on the base, entrypoint and command as prom/prometheus has them, user nobody."""
    (reference,) = [reference for reference in built if reference.startswith(f"{local_images.PROMETHEUS_IMAGE}:")]
    _, config, layers = archive_layers(built[reference])
    assert config["config"]["Entrypoint"] == ["/bin/prometheus"]
    assert config["config"]["Cmd"] == ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus"]
    assert config["config"]["User"] == "65534:65534" and config["config"]["WorkingDir"] == "/prometheus"
    assert {"bin/prometheus", "etc/prometheus/prometheus.yml"} <= {name.lstrip("./") for name in layers[-1]}
    aliases = local_images.image_aliases(built)
    assert aliases["kuberos.local/prometheus:debian"] == reference


def test_pause_image_holds_only_the_program(built):
    _, config, layers = archive_layers(built[local_images.PAUSE_IMAGE])
    assert config["config"]["Entrypoint"] == ["/pause"]
    assert [name for name in layers[0] if name not in (".", "./")] == ["pause"]


def test_ros_image_configuration(built, ros_image):
    _, config, layers = archive_layers(built[ros_image])
    env = dict(item.split("=", 1) for item in config["config"]["Env"])
    assert env["PATH"].split(":")[0] == "/opt/ros/jazzy/bin"
    assert env["PYTHONPATH"] == "/opt/kuberos" and env["_ROS_WHEELS_BOOTSTRAP_COMPLETE"] == "1"
    assert env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp" and env["ROS_LOG_DIR"] == "/tmp/ros"
    assert "/opt/ros/jazzy/lib" in env["LD_LIBRARY_PATH"].split(":")
    assert config["config"]["WorkingDir"] == "/opt/kuberos"
    assert not config["config"].get("Entrypoint") and not config["config"].get("Cmd")
    top = layers[-1]
    assert "opt/kuberos/kuberos_pnp/planner.py" in top
    assert "opt/kuberos/ansible_collections/kuberos/platform/plugins/module_utils/kuberos_controller/controller.py" in top
    assert not [name for name in top if "__pycache__" in name or name.endswith(".pyc")]


def test_changed_source_rebuilds_only_the_top_layer(built, ros_image, tmp_path):
    """A copy of the repository with one more source file, built against a copy of the cache's base."""
    copy = tmp_path / "repo"
    for name in local_images.REQUIREMENTS:
        (copy / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(os.path.join(ROOT, name), copy / name)
    for source, _ in local_images.APP_TREES:
        shutil.copytree(os.path.join(ROOT, source), copy / source, ignore=shutil.ignore_patterns("__pycache__"))
    (copy / local_images.PAUSE_SOURCE).parent.mkdir(parents=True)
    shutil.copy(os.path.join(ROOT, local_images.PAUSE_SOURCE), copy / local_images.PAUSE_SOURCE)
    os.symlink(os.path.join(ROOT, ".venv"), copy / ".venv")
    (copy / "sim" / "kuberos_pnp" / "_image_test_marker.py").write_text('"""Only in this copy."""\n', encoding="utf-8")

    cache = tmp_path / "cache"
    images = os.path.join(CACHE_DIR, "images")
    for name in os.listdir(images):  # the bases, hard-linked: building one again would take minutes
        if name.startswith("base-"):
            shutil.copytree(os.path.join(images, name), cache / "images" / name, copy_function=_link_or_copy)

    messages: list[str] = []
    started = time.monotonic()
    try:
        rebuilt = local_images.build_images(str(copy), str(cache), log=messages.append)
        elapsed = time.monotonic() - started
        changed, _, layers = archive_layers(rebuilt[f"{local_images.ROS_IMAGE}:{_ros_tag(rebuilt)}"])
    finally:
        shutil.rmtree(cache, ignore_errors=True)  # a third of a gigabyte that no later test uses
    assert not [message for message in messages if "debootstrap" in message], messages
    assert elapsed < 60, f"rebuilding the top layer took {elapsed:.0f}s"
    assert f"{local_images.ROS_IMAGE}:{_ros_tag(rebuilt)}" != ros_image
    original, _, _ = archive_layers(built[ros_image])
    assert [layer["digest"] for layer in changed["layers"][:-1]] == [layer["digest"] for layer in original["layers"][:-1]]
    assert changed["layers"][-1]["digest"] != original["layers"][-1]["digest"]
    assert "opt/kuberos/kuberos_pnp/_image_test_marker.py" in layers[-1]


def _ros_tag(built: dict[str, str]) -> str:
    (reference,) = [reference for reference in built if reference.startswith(f"{local_images.ROS_IMAGE}:")]
    return reference.rpartition(":")[2]


def _link_or_copy(source: str, destination: str) -> None:
    try:
        os.link(source, destination)
    except OSError:
        shutil.copy2(source, destination)


# --- importing and running ------------------------------------------------------------------------------------


def test_import_is_idempotent_and_aliases_share_the_digest(built, ros_image, containerd, imported):
    assert [line for line in imported if line.startswith("imported")], imported
    assert local_images.import_images("ctr", containerd.address, built, local_images.image_aliases(built)) == []
    images = containerd.images()
    ros_digest = local_images.archive_image(built[ros_image])[1]
    assert images[ros_image][0] == ros_digest
    assert images[local_images.PAUSE_IMAGE][0] == local_images.archive_image(built[local_images.PAUSE_IMAGE])[1]
    for alias, target in local_images.image_aliases(built).items():
        assert images[alias][0] == local_images.archive_image(built[target])[1], alias
        assert target != ros_image or images[alias][0] == ros_digest
    # The CRI plugin (the kubelet's view of the k8s.io namespace) takes up every name: it labels them managed.
    plugins = containerd.run("plugins", "ls").stdout
    if re.search(r"io\.containerd\.grpc\.v1\s+cri\s+\S+\s+ok", plugins):
        names = [*built, *local_images.image_aliases(built)]
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            images = containerd.images()
            if all("io.cri-containerd.image=managed" in images[name][1] for name in names):
                break
            time.sleep(0.5)
        for name in names:
            assert "io.cri-containerd.image=managed" in images[name][1], name


def test_ros_image_runs_the_modules(containerd, imported):
    """The modules' imports and rclpy with Fast DDS; and the venv's pycs are current (none is written anew)."""
    script = 'touch /tmp/before && python3 -c "$0" && find /opt/ros /usr -name "*.pyc" -newer /tmp/before | sed "s/^/stale /"'
    _, command = containerd.container("ghcr.io/kuberos/pnp-planner:0.1", "sh", "-c", script, MODULE_IMPORTS)
    done = subprocess.run(command, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "executable /opt/ros/jazzy/bin/python3" in done.stdout
    assert "stale " not in done.stdout, done.stdout[-3000:]


def test_ros_base_image_has_the_published_layout(built, ros_base_image):
    """As docker.io/library/ros:jazzy-ros-base: the entrypoint sources ROS, nothing of it is on PATH."""
    _, config, layers = archive_layers(built[ros_base_image])
    assert config["config"]["Entrypoint"] == ["/ros_entrypoint.sh"] and config["config"]["Cmd"] == ["bash"]
    env = dict(item.split("=", 1) for item in config["config"]["Env"])
    assert env["ROS_DISTRO"] == "jazzy"
    assert "ros" not in env["PATH"] and "LD_LIBRARY_PATH" not in env, env
    assert {"ros_entrypoint.sh", "opt/ros/jazzy/setup.bash"} <= set(layers[-1])


def test_published_layout_runs_the_discovery_server_only_through_its_entrypoint(containerd, imported):
    """`ctr run` replaces the whole argv: the entrypoint is given by hand here, as the kubelet prepends it to a
    pod's args. Without it, the program is not found: a pod whose `command` overrode the entrypoint fails so."""
    image = "docker.io/library/ros:jazzy-ros-base"
    _, command = containerd.container(image, "/ros_entrypoint.sh", "fast-discovery-server", "-h")
    done = subprocess.run(command, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "Usage" in done.stdout
    _, command = containerd.container(image, "fast-discovery-server", "-h")
    done = subprocess.run(command, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert done.returncode != 0 and "Usage" not in done.stdout
    assert "executable file not found" in done.stdout + done.stderr, done.stdout[-2000:] + done.stderr[-2000:]
    # rclpy through the entrypoint: the image's python3 is ROS's once the setup is sourced.
    check = "import rclpy, std_msgs.msg; print('rclpy ok')"
    _, command = containerd.container(image, "/ros_entrypoint.sh", "python3", "-c", check)
    done = subprocess.run(command, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert done.returncode == 0 and "rclpy ok" in done.stdout, done.stdout[-3000:] + done.stderr[-3000:]


def test_ros_image_runs_the_controller_and_bridge_as_their_pods_do(containerd, imported):
    """`python -m <entry>` not as root, on a read-only root filesystem (the controller's securityContext): as the
    image's own user (1000; this ctr cannot name another, and a non-root process cannot switch), as the pods run."""
    as_nobody = ("--read-only",)
    _, command = containerd.container("ghcr.io/kuberos/controller:0.2.0", "python", "-c", ENTRY_IMPORTS, options=as_nobody)
    done = subprocess.run(command, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "prefix /opt/ros/jazzy" in done.stdout
    for image, entry in (
        ("ghcr.io/kuberos/controller:0.2.0", "kuberos_controller"),
        ("ghcr.io/kuberos/bridge:0.2.0", "kuberos_bridge"),
    ):
        module = f"ansible_collections.kuberos.platform.plugins.module_utils.{entry}"
        _, command = containerd.container(image, "python", "-m", module, "--help", options=as_nobody)
        done = subprocess.run(command, capture_output=True, text=True, timeout=RUN_TIMEOUT)
        assert done.returncode == 0 and "usage:" in done.stdout, done.stdout[-3000:] + done.stderr[-3000:]


def test_pause_exits_zero_on_sigterm(containerd, imported):
    name, command = containerd.container(local_images.PAUSE_IMAGE)
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline and process.poll() is None:
            tasks = containerd.run("tasks", "ls").stdout
            if re.search(rf"^{name}\s+\d+\s+RUNNING", tasks, re.M):
                break
            time.sleep(0.2)
        else:
            pytest.fail(f"the pause container did not start: {process.poll()}")
        assert containerd.run("tasks", "kill", "-s", "SIGTERM", name).returncode == 0
        assert process.wait(timeout=20) == 0, process.stdout.read().decode(errors="replace")
    finally:
        if process.poll() is None:
            containerd.run("tasks", "kill", "-s", "SIGKILL", name)
            process.wait(timeout=20)
