"""Processes on a host: in its network namespace and cgroup, with the pod's volumes and the host's /dev/shm.

The launch chain, each step exec'ing the next (one pid, the session leader, throughout):

    sh -c JOIN            joins the cgroup(s), in the root namespaces (``ip netns exec`` remounts /sys)
    ip netns exec <ns>    network namespace, a private mount namespace, /etc/netns/<ns>/hosts on /etc/hosts
    sh -c MOUNTS          volumes at their mountPath, then the host's own /dev/shm (a directory of the run)
    <command>             as rendered

Every process of a host shares that host's /dev/shm and no other host's: Fast DDS takes participants with the
same network addresses for one machine and talks to them through shared memory only, so processes of one host
need one /dev/shm (as on a real node), and hosts must not share it (traffic between hosts crosses the fabric).

A mountPath that does not exist on this machine (``/etc/kuberos``) is made inside an overlay of its nearest
existing ancestor (upper layer in the run directory), so nothing outside the run directory changes; the
overlay hides ``ip netns exec``'s bind mounts below it, which are made again.
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import time
from dataclasses import dataclass, field

from ._core import ros_wheels
from .netns import ETC_NETNS

JOIN = 'for f in "$@"; do [ "$f" = -- ] && break; echo $$ > "$f"; shift; done; shift; exec "$@"'
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@dataclass(frozen=True)
class VolumeMount:
    source: str  # a directory in the run directory
    target: str  # the mountPath
    read_only: bool = False


def _ancestor(path: str) -> str:
    """The nearest existing directory above a path that does not exist."""
    parent = os.path.dirname(path)
    while not os.path.isdir(parent):
        parent = os.path.dirname(parent)
    return parent


def host_shm(shm_dir: str) -> str:
    """The shell line that puts the host's shared-memory directory on /dev/shm, then execs "$@"."""
    return f'mount --bind {shlex.quote(shm_dir)} /dev/shm && exec "$@"'


def mount_script(mounts: list[VolumeMount], netns: str, scratch: str, shm_dir: str | None = None) -> str:
    """Shell lines making ``mounts`` in the process's mount namespace, then /dev/shm: the host's ``shm_dir``, or
    a private one without it (ros_wheels.PRIVATE_SHM); the last line execs "$@"."""
    lines = ["set -e"]
    overlays: list[str] = []
    for mount in mounts:
        if not os.path.exists(mount.target):
            ancestor = _ancestor(mount.target)
            if ancestor == "/":
                raise ValueError(f"mountPath {mount.target}: no existing parent directory but /, which cannot be overlaid")
            if not any(ancestor == o or ancestor.startswith(o + "/") for o in overlays):
                overlays = [o for o in overlays if not o.startswith(ancestor + "/")] + [ancestor]
    for index, lower in enumerate(sorted(overlays)):
        upper, work = os.path.join(scratch, f"overlay{index}", "upper"), os.path.join(scratch, f"overlay{index}", "work")
        os.makedirs(upper, exist_ok=True)
        os.makedirs(work, exist_ok=True)
        options = f"lowerdir={lower},upperdir={upper},workdir={work}"
        lines.append(f"mount -t overlay kuberos-sim -o {shlex.quote(options)} {shlex.quote(lower)}")
    netns_dir = os.path.join(ETC_NETNS, netns)
    for name in sorted(os.listdir(netns_dir)) if os.path.isdir(netns_dir) else []:
        target = os.path.join("/etc", name)
        if any(target.startswith(o + "/") for o in overlays):
            lines.append(f"mount --bind {shlex.quote(os.path.join(netns_dir, name))} {shlex.quote(target)}")
    for mount in mounts:
        target = shlex.quote(mount.target)
        lines.append(f"mkdir -p {target}")
        lines.append(f"mount --bind {shlex.quote(mount.source)} {target}")
        if mount.read_only:
            lines.append(f"mount -o remount,bind,ro {target}")
    return "\n".join(lines) + "\n" + (host_shm(shm_dir) if shm_dir else ros_wheels.PRIVATE_SHM)


@dataclass
class SimProcess:
    """A process started on a host; ``log`` holds its stdout and stderr."""

    name: str
    host: str
    cgroup: str  # "node" or "hardware"
    command: tuple[str, ...]
    log: str
    popen: subprocess.Popen
    deployment: str | None = None
    started: float = field(default_factory=time.monotonic)

    @property
    def pid(self) -> int:
        return self.popen.pid

    @property
    def running(self) -> bool:
        return self.popen.poll() is None

    @property
    def returncode(self) -> int | None:
        return self.popen.poll()

    def output(self) -> str:
        try:
            with open(self.log, encoding="utf-8", errors="replace") as handle:
                return handle.read()
        except OSError:
            return ""

    def tail(self, lines: int = 20) -> str:
        state = "running" if self.running else f"exited {self.returncode}"
        body = "\n".join(self.output().splitlines()[-lines:])
        return f"--- {self.name} on {self.host} ({state}; log {self.log}) ---\n{body}"

    def signal(self, sig: int) -> None:
        if self.running:
            try:
                os.killpg(self.popen.pid, sig)  # its own session: this process and what it started
            except ProcessLookupError:
                pass


def launch(
    name: str,
    host: str,
    netns: str,
    procs_files: list[str],
    command: list[str],
    env: dict[str, str],
    mounts: list[VolumeMount],
    log: str,
    scratch: str,
    cgroup: str = "node",
    deployment: str | None = None,
    shm_dir: str | None = None,
) -> SimProcess:
    """Start ``command`` on the host: cgroup joined before exec, its own session, output to ``log``."""
    os.makedirs(scratch, exist_ok=True)
    if shm_dir:
        os.makedirs(shm_dir, mode=0o1777, exist_ok=True)
        os.chmod(shm_dir, 0o1777)
    script = mount_script(mounts, netns, scratch, shm_dir)
    argv = ["sh", "-c", JOIN, "sh", *procs_files, "--", "ip", "netns", "exec", netns, "sh", "-c", script, "sh", *command]
    with open(log, "ab") as out:
        popen = subprocess.Popen(
            argv, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True, cwd=scratch
        )
    return SimProcess(name, host, cgroup, tuple(command), log, popen, deployment)


def stop_all(processes: list[SimProcess], timeout: float) -> list[SimProcess]:
    """SIGINT, then SIGTERM, each with ``timeout`` seconds to exit, then SIGKILL; the processes that needed it."""
    killed = []
    for sig in STOP_SIGNALS:
        alive = [p for p in processes if p.running]
        for process in alive:
            process.signal(sig)
        deadline = time.monotonic() + timeout
        while any(p.running for p in alive) and time.monotonic() < deadline:
            time.sleep(0.05)
    for process in processes:
        if process.running:
            process.signal(signal.SIGKILL)
            killed.append(process)
    for process in processes:
        try:
            process.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
    return killed
