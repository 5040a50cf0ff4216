"""Lab machines: Debian machines booted with systemd-nspawn, each behaving as a separate host of a site.

The cluster setup roles (node_prereqs, kubeadm_init, kubeadm_join, cilium) run on them as on a real site: over
SSH as a non-root user with sudo (Ansible ``become``), against a real systemd that supervises containerd and the
kubelet, and with ``kubeadm init`` and ``join`` for real. A machine has:

- its own root filesystem: an overlay of one cached Debian root (``debootstrap --variant=minbase`` of bookworm with
  systemd, sshd, sudo, Python, containerd, runc and the programs kubeadm's preflight wants) and the machine's own
  upper directory, so everything kubeadm, the kubelet, etcd and Cilium write (``/etc/kubernetes``,
  ``/var/lib/kubelet``, ``/var/lib/etcd``, ``/etc/cni``, ``/opt/cni``) is the machine's alone; containerd's root
  (``/var/lib/containerd``) is a directory of its own bound in, because its overlayfs snapshots cannot live on an
  overlay;
- its own network stack: a network namespace with ``host0`` on the lab's bridge (an address in a subnet that exists
  only in the lab; ``/proc/sys/net`` is the machine's own). A machine is on the site's network (``site``, with a
  default route through this machine), on the lab's stand-in for the internet (``wan``: a second /24 on the same
  bridge with no route to the site, as a cloud VM is), or on both (``site+wan``: a VPN gateway with a public
  address). This machine routes the networks given to ``--route`` through a machine, as a site's router would;
- its own cgroup subtree: ``/sys/fs/cgroup/<controller>/kuberos-lab-<tag>/<name>`` in every v1 hierarchy, entered
  before the machine boots in a cgroup namespace of its own. A unit of the lab's root (``kuberos-lab-cgroups``)
  mounts the v1 controllers afresh and writable inside, where the namespace makes the subtree its root: the
  kubelet's ``/kubepods`` and containerd's containers are under the machine's subtree, never beside another's;
- its own systemd (PID 1), journal, sshd with an ed25519 host key made for it, hostname, machine id and
  ``/etc/hosts`` naming every lab machine;
- the lab's user ``kuberos`` with the lab's SSH key and password-less sudo (what Ansible's ``become`` needs).

What the machines share with this machine: the kernel (no WireGuard module, no IPIP; VXLAN and netfilter work),
``/dev/kmsg`` (the kubelet reads it), ``/dev/net/tun`` (wireguard-go's), ``/lib/modules`` (read-only), and the
kernel settings outside a network namespace. The kubelet sets some of those (``kernel.panic``,
``vm.overcommit_memory``, ...): their values from before the lab started are saved and restored by
`MachineLab.down`, which also removes every mount, cgroup, namespace, link and route the lab made, leaving the host
as it was.

Why systemd-nspawn: this machine runs no systemd, and the roles need one (their units, ``systemctl``, kubeadm's
``kubelet.service`` drop-in). nspawn boots a real systemd as the machine's PID 1 from a plain root directory, with
no container runtime of its own and no daemon (``--register=no --keep-unit``: nothing on this machine to register
with). It is run with ``SYSTEMD_NSPAWN_API_VFS_WRITABLE=1`` and every capability, as kind runs its node containers
privileged: a kubelet needs to write kernel settings and cgroups.

Used by the molecule scenarios (``python -m ...kuberos_lab.machines up|down``) and the site chain test. Needs root,
debootstrap, systemd-nspawn (Debian's systemd-container), iproute2, util-linux and ssh-keygen.

    python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.machines up --state DIR \\
        --machine cp-1:edge,control_plane:site+wan --machine fetch-1:robots --machine vm-1:cloud:wan \
        --route 10.99.0.0/24:cp-1
    python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.machines down --state DIR
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
import zlib
from dataclasses import asdict, dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import background_process as bg
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import local_images as li

RECIPE_VERSION = "1"
SUITE = "bookworm"
MIRROR = os.environ.get("KUBEROS_DEBIAN_MIRROR", "http://deb.debian.org/debian")
# What the machine image holds: a booting Debian with sshd and sudo, Ansible's needs (python3, python3-apt), and
# what node_prereqs installs (present already, as a site's golden image would have them: the lab has no mirror).
PACKAGES = (
    "systemd", "systemd-sysv", "dbus", "openssh-server", "sudo", "python3", "python3-apt", "iproute2", "iptables",
    "kmod", "procps", "ca-certificates", "gpg", "containerd", "runc", "conntrack", "ethtool", "socat", "ebtables",
    "util-linux", "mount", "keepalived", "wireguard-tools", "wireguard-go",
)  # fmt: skip
USER = "kuberos"
NETWORKS = ("site", "wan", "site+wan")
MIRROR_PORT = 5445  # the lab registry's port on the bridge (--mirror)
CGROUP_ROOT = bg.CGROUP_ROOT
# The kubelets' evictionHard in the lab (kuberos_kubelet_eviction_hard): every signal the kubelet watches by default,
# with the disk ones at 1%, because all machines share the host's one disk and its free share is not theirs.
LAB_EVICTION_HARD = {
    "memory.available": "100Mi",
    "nodefs.available": "1%",
    "nodefs.inodesFree": "1%",
    "imagefs.available": "1%",
    "imagefs.inodesFree": "1%",
}
# Kernel settings outside a network namespace that a kubelet or kube-proxy in a machine writes.
HOST_SYSCTLS = (
    "kernel/panic", "kernel/panic_on_oops", "vm/overcommit_memory", "vm/panic_on_oom", "kernel/keys/root_maxkeys",
    "kernel/keys/root_maxbytes", "net/netfilter/nf_conntrack_max", "fs/inotify/max_user_instances",
    "fs/inotify/max_user_watches",
)  # fmt: skip
# Every machine's root is this machine's root user: inotify's per-user limits are shared by all their kubelets,
# kube-proxies and containerds. Raised while the lab runs (kind's nodes need the same), restored by ``down``.
INOTIFY_LIMITS = {"fs/inotify/max_user_instances": 8192, "fs/inotify/max_user_watches": 524288}
BOOT_TIMEOUT = 180.0  # for all the machines of one call, booting side by side on a busy machine
CGROUPS_SCRIPT = """#!/bin/sh
# Lab machines only (kuberos_lab.machines): mount every cgroup v1 controller afresh and writable. This machine runs
# in a cgroup namespace of its own, so each fresh mount shows the machine's own subtree as its root.
set -e
for controller in cpuset cpu cpuacct blkio memory devices freezer pids net_cls net_prio perf_event hugetlb; do
  grep -qw "$controller" /proc/cgroups || continue
  dir=/sys/fs/cgroup/$controller
  if mountpoint -q "$dir"; then umount "$dir" || umount -l "$dir"; fi
  mkdir -p "$dir" 2>/dev/null || true
  mount -t cgroup -o rw,nosuid,nodev,noexec,"$controller" cgroup "$dir" || true
done
"""
CGROUPS_UNIT = """[Unit]
Description=Lab machine: writable cgroup v1 controllers (kuberos_lab.machines)
DefaultDependencies=no
# First of all: a unit whose cgroup systemd makes while the controllers are mounted afresh fails to start.
Before=sysinit.target systemd-modules-load.service systemd-tmpfiles-setup.service systemd-tmpfiles-setup-dev.service
Before=systemd-sysctl.service systemd-journal-flush.service systemd-update-utmp.service dbus.service ssh.service
Before=containerd.service kubelet.service

[Service]
Type=oneshot
RemainAfterExit=yes
ExecStart=/usr/local/sbin/kuberos-lab-cgroups

[Install]
WantedBy=sysinit.target
"""


class MachineError(RuntimeError):
    """A lab machine could not be made, booted or removed; the message says which and why."""


def run(*command: str, check: bool = True, timeout: float = 60, **kwargs) -> subprocess.CompletedProcess:
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False, **kwargs)
    except (OSError, subprocess.TimeoutExpired) as error:
        raise MachineError(f"{' '.join(command)}: {error}") from error
    if check and done.returncode != 0:
        raise MachineError(f"{' '.join(command)} exited {done.returncode}: {(done.stderr or done.stdout).strip()[-2000:]}")
    return done


def missing_requirements() -> list[str]:
    """What this machine lacks for lab machines (empty: all there)."""
    problems = []
    if os.geteuid() != 0:
        problems.append("root")
    for program in ("systemd-nspawn", "debootstrap", "ip", "unshare", "nsenter", "ssh-keygen", "mount"):
        if not shutil.which(program):
            problems.append(program)
    if not os.path.isdir(os.path.join(CGROUP_ROOT, "memory")):
        problems.append("cgroup v1 hierarchies under /sys/fs/cgroup")
    return problems


# --- the machine image ------------------------------------------------------------------------------------------


def image_key() -> str:
    import hashlib

    return hashlib.sha256("\0".join([RECIPE_VERSION, SUITE, *PACKAGES, CGROUPS_SCRIPT, CGROUPS_UNIT]).encode()).hexdigest()[:12]


def build_image(cache_dir: str, log=print) -> str:
    """The machines' Debian root, built once per recipe under ``<cache_dir>/machines/root-<key>`` (debootstrap, about
    a minute), with the lab's cgroup unit, the lab user and no SSH host keys (each machine gets its own)."""
    folder = os.path.join(os.path.abspath(os.path.expanduser(cache_dir)), "machines")
    key = image_key()
    root = os.path.join(folder, f"root-{key}")
    if os.path.exists(os.path.join(root, ".kuberos-lab-image")):
        return root
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, ".lock"), "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if os.path.exists(os.path.join(root, ".kuberos-lab-image")):
            return root
        work = os.path.join(folder, f"tmp-{key}-{os.getpid()}")
        _remove_tree(work)
        started = time.monotonic()
        log(f"lab machines: debootstrap {SUITE} with {len(PACKAGES)} packages into {work} (about a minute)")
        done = subprocess.run(
            li.debootstrap_command(SUITE, work, MIRROR, PACKAGES),
            capture_output=True, text=True, timeout=1800, check=False,
        )  # fmt: skip
        if done.returncode != 0:
            _remove_tree(work)
            raise MachineError(f"debootstrap of the lab machines' root failed (exit {done.returncode}):\n{done.stdout[-3000:]}")
        _customise(work)
        with open(os.path.join(work, ".kuberos-lab-image"), "w", encoding="utf-8") as handle:
            json.dump({"key": key, "packages": PACKAGES, "suite": SUITE}, handle)
        for old in os.listdir(folder):
            if old.startswith("root-") and old != f"root-{key}":
                _remove_tree(os.path.join(folder, old))
        os.replace(work, root)
        log(f"lab machines: root {root} built in {time.monotonic() - started:.0f}s")
    return root


def _customise(root: str) -> None:
    def write(relative: str, text: str, mode: int = 0o644) -> None:
        path = os.path.join(root, relative)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w", encoding="utf-8") as handle:
            handle.write(text)
        os.chmod(path, mode)

    write("usr/local/sbin/kuberos-lab-cgroups", CGROUPS_SCRIPT, 0o755)
    write("etc/systemd/system/kuberos-lab-cgroups.service", CGROUPS_UNIT)
    wants = os.path.join(root, "etc/systemd/system/sysinit.target.wants")
    os.makedirs(wants, exist_ok=True)
    with contextlib.suppress(FileExistsError):
        os.symlink("/etc/systemd/system/kuberos-lab-cgroups.service", os.path.join(wants, "kuberos-lab-cgroups.service"))
    run("chroot", root, "useradd", "--create-home", "--shell", "/bin/bash", "--uid", "1000", USER)
    write(f"etc/sudoers.d/{USER}", f"{USER} ALL=(ALL) NOPASSWD:ALL\n", 0o440)
    write("etc/ssh/sshd_config.d/kuberos-lab.conf", "PasswordAuthentication no\nPermitRootLogin no\nUseDNS no\n")
    for name in os.listdir(os.path.join(root, "etc/ssh")):
        if name.startswith("ssh_host_"):
            os.unlink(os.path.join(root, "etc/ssh", name))
    for relative in ("etc/machine-id", "var/lib/dbus/machine-id"):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(os.path.join(root, relative))
    write("etc/machine-id", "")  # empty: systemd uses the id nspawn passes (--uuid)
    # No swap, no getty on the console, no units that wait for hardware.
    for unit in ("getty@tty1.service", "console-getty.service"):
        with contextlib.suppress(FileExistsError):
            os.symlink("/dev/null", os.path.join(root, "etc/systemd/system", unit))


# --- machines ------------------------------------------------------------------------------------------------------


@dataclass
class Machine:
    name: str
    groups: list[str]
    address: str
    host_key: str = ""
    uuid: str = ""
    leader: int = 0  # the machine's PID 1 as this machine sees it
    networks: str = "site"  # site, wan or site+wan
    wan_address: str = ""  # its address on the lab's stand-in for the internet (networks wan and site+wan)

    @property
    def unit(self) -> str:
        return self.name


@dataclass
class MachineLab:
    state: str
    tag: str = "kl"
    subnet: str = "10.213.0"  # a /24 of the lab only: .1 is this machine on the bridge, machines from .11
    wan_subnet: str = ""  # the stand-in for the internet, another /24 on the bridge; empty: the subnet's next /24
    routes: dict[str, str] = field(default_factory=dict)  # network -> machine this machine routes it through
    cache_dir: str = ""
    machines: dict[str, Machine] = field(default_factory=dict)
    sysctls: dict[str, str] = field(default_factory=dict)

    # -- names ---------------------------------------------------------------------------------------------------
    @property
    def bridge(self) -> str:
        return f"{self.tag}br0"

    @property
    def gateway(self) -> str:
        return f"{self.subnet}.1"

    @property
    def wan(self) -> str:
        if self.wan_subnet:
            return self.wan_subnet
        first, second, third = self.subnet.split(".")
        return f"{first}.{second}.{int(third) + 1}"

    @property
    def admin_key(self) -> str:
        return os.path.join(self.state, "admin_ed25519")

    @property
    def known_hosts(self) -> str:
        return os.path.join(self.state, "known_hosts")

    @property
    def inventory(self) -> str:
        return os.path.join(self.state, "inventory.yml")

    def netns(self, name: str) -> str:
        return f"{self.tag}-{name}"

    def veth(self, name: str) -> str:
        short = f"{self.tag}v-{name}"
        return short if len(short) <= 15 else f"{self.tag}v{zlib.crc32(name.encode()):08x}"

    def home(self, name: str, *parts: str) -> str:
        return os.path.join(self.state, "machines", name, *parts)

    def rootfs(self, name: str) -> str:
        return self.home(name, "rootfs")

    def cgroup(self, name: str) -> str:
        return f"kuberos-lab-{self.tag}/{name}"

    def machine_name(self, name: str) -> str:
        return f"{self.tag}-{name}"

    def stale(self, names: list[str]) -> list[str]:
        """Of machines this lab is about to make, the network namespaces that exist already: another lab's, left up."""
        return [self.netns(name) for name in names if os.path.exists(f"/var/run/netns/{self.netns(name)}")]

    # -- lifecycle -----------------------------------------------------------------------------------------------
    def up(self, specs: list[tuple[str, list[str]] | tuple[str, list[str], str]], log=print) -> MachineLab:
        """Make and boot every machine ``(name, groups[, networks])``; write the inventory and known_hosts."""
        problems = missing_requirements()
        if problems:
            raise MachineError("lab machines need: " + ", ".join(problems))
        stale = self.stale([spec[0] for spec in specs if spec[0] not in self.machines])
        if stale:
            raise MachineError(
                f"lab machines of an earlier run are still up here ({', '.join(stale)}: their network namespaces "
                f"exist), an interrupted test's perhaps: take that lab down first (python -m {__name__} down --state "
                "<its state folder> --remove, or site_lab's down), or remove them (machinectl list; ip netns list)"
            )
        os.makedirs(self.state, exist_ok=True)
        image = build_image(self.cache_dir or "~/.cache/kuberos", log)
        if not os.path.exists(self.admin_key):
            run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", "kuberos-lab-admin", "-f", self.admin_key)
        self._save_sysctls()
        self._bridge()
        for name, groups, *rest in specs:
            networks = rest[0] if rest else "site"
            if networks not in NETWORKS:
                raise MachineError(f"{name}: networks must be one of {', '.join(NETWORKS)}, got {networks!r}")
            if name not in self.machines:
                host = 11 + len(self.machines)  # never reused while the lab stands: machines join later too
                self.machines[name] = Machine(
                    name,
                    list(groups),
                    f"{self.subnet}.{host}" if "site" in networks else f"{self.wan}.{host}",
                    uuid=uuid.uuid4().hex,
                    networks=networks,
                    wan_address=f"{self.wan}.{host}" if "wan" in networks else "",
                )
        for network, through in self.routes.items():
            if through not in self.machines or "site" not in self.machines[through].networks:
                raise MachineError(f"--route {network}:{through}: {through} is not a machine on the site's network")
        self.save()
        for machine in self.machines.values():
            self._prepare(machine, image)
        self._routes()
        self.save()
        for machine in self.machines.values():
            self._boot(machine)
        self.save()
        deadline = time.monotonic() + BOOT_TIMEOUT
        for machine in self.machines.values():
            try:
                self._wait_booted(machine, deadline)
            except MachineError as error:  # seen rarely, on a busy machine: power it off and boot it once more
                log(f"lab machines: {error}; booting {machine.name} again")
                self._stop(machine)
                self._boot(machine)
                self.save()
                self._wait_booted(machine, time.monotonic() + BOOT_TIMEOUT)
        self.save()  # the leaders as found once booted
        self.write_known_hosts()
        self.write_inventory()
        return self

    def registry(self):
        """The lab's registry (``--mirror``): on the bridge, TLS, pulls without credentials, state under DIR/registry."""
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.registry import LocalRegistry

        return LocalRegistry(os.path.join(self.state, "registry"), self.gateway, MIRROR_PORT, auth=False)

    def down(self, remove: bool = False) -> None:
        """Power every machine off (and kill what is left), unmount, remove cgroups, namespaces, links; restore the
        kernel settings the machines changed; stop the lab's registry if it runs."""
        if os.path.isdir(os.path.join(self.state, "registry")):
            self.registry().stop(remove=remove)
        self._stop_all(list(self.machines.values()))
        for machine in self.machines.values():
            self._unmount(machine.name)
            self._remove_cgroups(machine.name)
            run("ip", "netns", "delete", self.netns(machine.name), check=False)
            run("ip", "link", "delete", self.veth(machine.name), check=False)
            shutil.rmtree(f"/run/systemd/nspawn/propagate/{self.machine_name(machine.name)}", ignore_errors=True)
        for hierarchy in bg.cgroup_hierarchies():
            with contextlib.suppress(OSError):
                os.rmdir(os.path.join(hierarchy, f"kuberos-lab-{self.tag}"))
        run("ip", "link", "delete", self.bridge, check=False)
        self._restore_sysctls()
        if remove:
            for machine in self.machines.values():
                _remove_tree(self.home(machine.name))
            shutil.rmtree(self.state, ignore_errors=True)

    # -- state ---------------------------------------------------------------------------------------------------
    def save(self) -> None:
        with open(os.path.join(self.state, "lab.json"), "w", encoding="utf-8") as handle:
            json.dump(asdict(self), handle, indent=1)

    @classmethod
    def load(cls, state: str) -> MachineLab:
        with open(os.path.join(state, "lab.json"), encoding="utf-8") as handle:
            data = json.load(handle)
        machines = {name: Machine(**values) for name, values in data.pop("machines").items()}
        return cls(**data, machines=machines)

    def _save_sysctls(self) -> None:
        if not self.sysctls:  # the values from before the first machine booted, never the kubelet's
            self.sysctls = {key: _read(f"/proc/sys/{key}") for key in HOST_SYSCTLS if os.path.exists(f"/proc/sys/{key}")}
        for key, least in INOTIFY_LIMITS.items():
            if os.path.exists(f"/proc/sys/{key}") and int(_read(f"/proc/sys/{key}") or 0) < least:
                _write(f"/proc/sys/{key}", str(least))

    def _restore_sysctls(self) -> None:
        for key, value in self.sysctls.items():
            if value and _read(f"/proc/sys/{key}") != value:
                with contextlib.suppress(OSError), open(f"/proc/sys/{key}", "w", encoding="utf-8") as handle:
                    handle.write(value)

    # -- network -------------------------------------------------------------------------------------------------
    def _bridge(self) -> None:
        if not os.path.exists(f"/sys/class/net/{self.bridge}"):
            run("ip", "link", "add", self.bridge, "type", "bridge")
            run("ip", "addr", "add", f"{self.gateway}/24", "dev", self.bridge)
            run("ip", "addr", "add", f"{self.wan}.1/24", "dev", self.bridge)
        run("ip", "link", "set", self.bridge, "up")

    def _routes(self) -> None:  # after the bridge is up; they go with it
        for network, through in self.routes.items():
            run("ip", "route", "replace", network, "via", self.machines[through].address, "dev", self.bridge)

    def _netns(self, machine: Machine) -> None:
        netns, veth = self.netns(machine.name), self.veth(machine.name)
        if not os.path.exists(f"/var/run/netns/{netns}"):
            run("ip", "netns", "add", netns)
        if not os.path.exists(f"/sys/class/net/{veth}"):
            run("ip", "link", "add", veth, "type", "veth", "peer", "name", "host0", "netns", netns)
        run("ip", "link", "set", veth, "master", self.bridge, "up")
        inside = ["ip", "-n", netns]
        have = run(*inside, "-4", "addr", "show", "dev", "host0").stdout
        for address in {machine.address, machine.wan_address} - {""}:
            if f"inet {address}/" not in have:
                run(*inside, "addr", "add", f"{address}/24", "dev", "host0")
        run(*inside, "link", "set", "host0", "up")
        run(*inside, "link", "set", "lo", "up")
        # The default route: the site's router for a site machine; for a wan machine (a cloud VM) the internet's
        # gateway, as its provider gives it: the site's network is reached only through the VPN's routes.
        run(*inside, "route", "replace", "default", "via", self.gateway if "site" in machine.networks else f"{self.wan}.1")

    # -- file system ---------------------------------------------------------------------------------------------
    def _prepare(self, machine: Machine, image: str) -> None:
        rootfs = self.rootfs(machine.name)
        for part in ("upper", "work", "rootfs", "containerd"):
            os.makedirs(self.home(machine.name, part), exist_ok=True)
        if not os.path.ismount(rootfs):
            run("mount", "-t", "overlay", "overlay", "-o",
                f"lowerdir={image},upperdir={self.home(machine.name, 'upper')},workdir={self.home(machine.name, 'work')}",
                rootfs)  # fmt: skip
        _write(os.path.join(rootfs, "etc/hostname"), machine.name + "\n")
        hosts = "127.0.0.1 localhost\n" + "".join(f"{m.address} {m.name}\n" for m in self.machines.values())
        _write(os.path.join(rootfs, "etc/hosts"), hosts)
        key = os.path.join(rootfs, "etc/ssh/ssh_host_ed25519_key")
        if not os.path.exists(key):
            run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"root@{machine.name}", "-f", key)
        with open(key + ".pub", encoding="utf-8") as handle:
            machine.host_key = " ".join(handle.read().split()[:2])
        ssh = os.path.join(rootfs, "home", USER, ".ssh")
        os.makedirs(ssh, exist_ok=True)
        with open(self.admin_key + ".pub", encoding="utf-8") as handle:
            _write(os.path.join(ssh, "authorized_keys"), handle.read())
        for path in (ssh, os.path.join(ssh, "authorized_keys")):
            os.chown(path, 1000, 1000)
        os.chmod(ssh, 0o700)
        self._netns(machine)
        self._cgroups(machine.name)

    def _cgroups(self, name: str) -> None:
        for hierarchy in bg.cgroup_hierarchies():
            path = hierarchy
            for part in self.cgroup(name).split("/"):
                path = os.path.join(path, part)
                os.makedirs(path, exist_ok=True)
                if os.path.basename(hierarchy) == "cpuset":  # a new cpuset has no CPUs until given its parent's
                    for setting in ("cpuset.cpus", "cpuset.mems"):
                        if not _read(os.path.join(path, setting)):
                            _write(os.path.join(path, setting), _read(os.path.join(os.path.dirname(path), setting)))

    def _unmount(self, name: str) -> None:
        for point in li._mounts_under(self.home(name)):
            if run("umount", point, check=False).returncode != 0:
                run("umount", "-l", point, check=False)

    def _remove_cgroups(self, name: str) -> None:
        for hierarchy in bg.cgroup_hierarchies():
            top = os.path.join(hierarchy, self.cgroup(name))
            for _attempt in range(50):
                pids = [pid for procs in _walk_procs(top) for pid in procs]
                if not pids:
                    break
                for pid in pids:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                time.sleep(0.1)
            for directory, _subdirectories, _files in sorted(os.walk(top), key=lambda entry: -len(entry[0])):
                with contextlib.suppress(OSError):
                    os.rmdir(directory)

    # -- processes -----------------------------------------------------------------------------------------------
    def _nspawn(self, machine: Machine) -> list[str]:
        return [
            "unshare", "--cgroup", "systemd-nspawn", "--quiet", "--directory", self.rootfs(machine.name), "--boot",
            "--register=no", "--keep-unit", f"--machine={self.machine_name(machine.name)}",
            f"--hostname={machine.name}", f"--uuid={machine.uuid}",
            f"--network-namespace-path=/var/run/netns/{self.netns(machine.name)}",
            # beside nspawn's default filter: the kernel keyring (containerd), bpf and perf_event_open (the CNI's
            # agent loads eBPF programs and reads their events through perf rings)
            "--capability=all", "--system-call-filter=@keyring bpf perf_event_open",
            f"--bind={self.home(machine.name, 'containerd')}:/var/lib/containerd",
            "--bind-ro=/lib/modules", "--bind=/dev/kmsg", "--bind=/dev/net/tun", "--console=passive",
        ]  # fmt: skip

    def _boot(self, machine: Machine) -> None:
        if machine.leader and _alive_leader(machine.leader, machine.name):
            return
        cgroups = [os.path.join(h, self.cgroup(machine.name), "cgroup.procs") for h in bg.cgroup_hierarchies()]

        def enter_cgroups() -> None:  # in the child, before exec: the machine's subtree becomes its cgroup namespace
            os.setsid()
            for procs in cgroups:
                with open(procs, "w", encoding="utf-8") as handle:
                    handle.write(str(os.getpid()))

        log = open(self.home(machine.name, "console.log"), "ab")
        env = {**os.environ, "SYSTEMD_NSPAWN_API_VFS_WRITABLE": "1", "SYSTEMD_NSPAWN_TMPFS_TMP": "1"}
        process = subprocess.Popen(
            self._nspawn(machine), stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env, preexec_fn=enter_cgroups
        )
        log.close()
        with open(self.home(machine.name, "nspawn.pid"), "w", encoding="utf-8") as handle:
            handle.write(str(process.pid))
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            leader = _leader(process.pid)
            if leader:
                machine.leader = leader
                return
            if process.poll() is not None:
                break
            time.sleep(0.1)
        raise MachineError(f"{machine.name} did not start: {self._console_tail(machine.name)}")

    def _wait_booted(self, machine: Machine, deadline: float) -> None:
        state = ""
        while time.monotonic() < deadline:
            if not _alive_leader(machine.leader, machine.name):  # found before nspawn had exec'd the machine's init
                launcher = _read(self.home(machine.name, "nspawn.pid"))
                machine.leader = (_leader(int(launcher)) if launcher.isdigit() else 0) or machine.leader
            asked = self.exec(machine.name, "systemctl", "is-system-running", check=False)
            state = asked.stdout.strip() or f"not answering: {asked.stderr.strip()[-200:]}"
            if state in ("running", "degraded") and _port_open(machine.address, 22):
                if state == "degraded":
                    failed = self.exec(machine.name, "systemctl", "--failed", "--plain", "--no-legend", check=False).stdout
                    journal = self.exec(machine.name, "journalctl", "-b", "-p", "warning", "-n", "15", "--no-pager", check=False)
                    raise MachineError(f"{machine.name} booted degraded, failed units:\n{failed}{journal.stdout}")
                return
            time.sleep(0.3)
        raise MachineError(f"{machine.name} did not finish booting in {BOOT_TIMEOUT:.0f}s (state {state or 'unknown'}): "
                           f"{self._console_tail(machine.name)}")  # fmt: skip

    def _stop(self, machine: Machine, timeout: float = 30.0) -> None:
        self._stop_all([machine], timeout)

    def _stop_all(self, machines: list[Machine], timeout: float = 30.0) -> None:
        """Power the machines off side by side (systemctl poweroff, or SIGTERM to nspawn), then wait for each;
        kill what is left after ``timeout``."""
        running = {}
        for machine in machines:
            pid = _read(self.home(machine.name, "nspawn.pid"))
            if pid.isdigit() and _is_nspawn(int(pid), self.rootfs(machine.name)):
                running[machine.name] = int(pid)
                if machine.leader and _alive_leader(machine.leader, machine.name):
                    self.exec(machine.name, "systemctl", "poweroff", "--no-block", check=False)
                else:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(int(pid), signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for machine in machines:
            nspawn = running.get(machine.name)
            while nspawn and time.monotonic() < deadline and _is_nspawn(nspawn, self.rootfs(machine.name)):
                time.sleep(0.2)
            if nspawn and _is_nspawn(nspawn, self.rootfs(machine.name)):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(nspawn, signal.SIGKILL)
            machine.leader = 0

    def power_off(self, name: str) -> None:
        """Cut one machine's power, as a host that fails: its PID 1 killed, nothing shut down cleanly (its files
        stay; ``down`` removes them)."""
        machine = self.machines[name]
        if machine.leader and _alive_leader(machine.leader, machine.name):
            with contextlib.suppress(ProcessLookupError):
                os.kill(machine.leader, signal.SIGKILL)  # the machine's PID namespace ends with its PID 1
        self._stop(machine)

    def rebuild(self, name: str, log=print) -> None:
        """Replace one machine by a new one of the same name and address, as a failed host rebuilt from a bare disk:
        its power cut, its disk (the overlay's upper layer, containerd's state) and its network stack (interfaces,
        addresses, netfilter rules: a new kernel's) thrown away, booted fresh from the image, with a new SSH host key
        (known_hosts rewritten)."""
        machine = self.machines[name]
        self.power_off(name)
        self._unmount(name)
        self._remove_cgroups(name)
        for part in ("upper", "work", "containerd"):
            _remove_tree(self.home(name, part))
        run("ip", "netns", "delete", self.netns(name), check=False)
        run("ip", "link", "delete", self.veth(name), check=False)
        self._prepare(machine, build_image(self.cache_dir or "~/.cache/kuberos", log))
        self._routes()
        self.save()
        self._boot(machine)
        self.save()
        self._wait_booted(machine, time.monotonic() + BOOT_TIMEOUT)
        self.save()
        self.write_known_hosts()
        log(f"lab machines: {name} rebuilt ({machine.address})")

    def exec(self, name: str, *command: str, check: bool = True, timeout: float = 60) -> subprocess.CompletedProcess:
        """Run a command inside a machine (all its namespaces), as root."""
        machine = self.machines[name]
        return run("nsenter", "--target", str(machine.leader), "--all", "--", *command, check=check, timeout=timeout)

    def _console_tail(self, name: str) -> str:
        return _read(self.home(name, "console.log"))[-1500:] or "(no output)"

    # -- access --------------------------------------------------------------------------------------------------
    def write_known_hosts(self) -> None:
        _write(self.known_hosts, "".join(f"{m.address} {m.host_key}\n" for m in self.machines.values()))

    def connection_vars(self) -> dict:
        return {
            "ansible_user": USER,
            "ansible_become": True,
            "ansible_ssh_private_key_file": self.admin_key,
            "ansible_ssh_common_args": f"-o UserKnownHostsFile={self.known_hosts} -o StrictHostKeyChecking=yes",
            "ansible_python_interpreter": "/usr/bin/python3",
        }

    def write_inventory(self) -> None:
        import yaml

        children: dict = {}
        for machine in self.machines.values():
            for group in machine.groups:
                children.setdefault(group, {"hosts": {}})["hosts"][machine.name] = {
                    "ansible_host": machine.address,
                    "kuberos_address": machine.address,
                }
        with open(self.inventory, "w", encoding="utf-8") as handle:
            yaml.safe_dump({"all": {"vars": self.connection_vars(), "children": children}}, handle, sort_keys=False)


# --- host inspection ---------------------------------------------------------------------------------------------


def _read(path: str) -> str:
    try:
        with open(path, encoding="utf-8") as handle:
            return handle.read().strip()
    except OSError:
        return ""


def _write(path: str, text: str) -> None:
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(text)


def _walk_procs(top: str):
    for directory, _subdirectories, files in os.walk(top):
        if "cgroup.procs" in files:
            yield [int(p) for p in _read(os.path.join(directory, "cgroup.procs")).split() if p.isdigit()]


def _remove_tree(path: str) -> None:
    for point in li._mounts_under(path):
        if run("umount", point, check=False).returncode != 0:
            run("umount", "-l", point, check=False)
    shutil.rmtree(path, ignore_errors=True)


def _is_nspawn(pid: int, rootfs: str) -> bool:
    argv = bg.cmdline(pid)
    return bool(argv) and "systemd-nspawn" in " ".join(argv[:3]) and rootfs in argv


def _children(pid: int) -> list[int]:
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            stat = _read(f"/proc/{entry}/stat")
            if stat and stat.rsplit(")", 1)[-1].split()[1] == str(pid):
                found.append(int(entry))
    return found


def _leader(launcher: int) -> int:
    """The machine's PID 1 (as this machine numbers it): the child of systemd-nspawn that runs systemd (``unshare``
    execs nspawn, so the launcher's pid is nspawn's)."""
    for child in _children(launcher):
        argv = bg.cmdline(child)
        # not nspawn's own child before it execs the machine's init: its argv[0] is still systemd-nspawn
        if argv and os.path.basename(argv[0]) in ("systemd", "init"):
            return child
    return 0


def _alive_leader(pid: int, name: str) -> bool:
    return bool(bg.cmdline(pid)) and _read(f"/proc/{pid}/root/etc/hostname") == name


def _port_open(address: str, port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection((address, port), timeout=0.5):
        return True
    return False


def _release(version: str) -> tuple[int, ...]:
    """``v1.33.7`` -> (1, 33, 7)."""
    match = re.fullmatch(r"v(\d+)\.(\d+)\.(\d+)", version)
    if not match:
        raise MachineError(f"a Kubernetes release looks like v1.34.4, got {version!r}")
    return tuple(int(part) for part in match.groups())


def kubernetes_programs(cache: str, version: str, names: tuple[str, ...] = ("kubelet", "kubeadm")) -> dict[str, str]:
    """{program: path} of the built ``names`` at ``version`` in ``<cache>/bin``; MachineError naming the build that
    makes them when one is missing."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import kubeadm_images

    found = {name: os.path.join(cache, "bin", f"{name}-{version}") for name in names}
    missing = [path for path in found.values() if not os.path.exists(path)]
    if missing:
        pinned = kubeadm_images.pinned_versions()["kubernetes"]
        hint = "make binaries WITH_KUBEADM=1 WITH_NODES=1" if version == pinned else kubeadm_images.build_command(version)
        raise MachineError(f"not built yet: {', '.join(missing)} ({hint})")
    return found


def site_vars(cache_dir: str, log=print, kubernetes_version: str | None = None) -> dict:
    """The lab's choices for the cluster setup roles, as inventory variables (each a documented role variable a real
    site may set too): the cgroupfs driver (systemd in a machine does not own the cgroup controllers the lab mounts),
    kubelet and kubeadm from the programs built here instead of the package repository, the images kubeadm runs
    preloaded from archives built here (with Cilium's, built from its Go module, and a busybox image for network
    checks), Cilium as the pod network (``kuberos_cni``), and the etcd and CoreDNS versions the project builds.

    ``kubernetes_version`` (None: the pinned one) builds the site at an older release, to be upgraded to the pinned
    one: its kubelet and kubeadm, and the images of both releases (kubeadm's images at the pinned version are preloaded
    or mirrored too, as a site stages them before an upgrade); ``kuberos_lab_upgrade_binaries`` then names the pinned
    release's kubelet and kubeadm (and kubectl when built) for the upgrade to install. etcd and CoreDNS stay the
    pinned ones, which both releases support. The sandbox image stays the role's default (1.34's pause 3.10.1, built
    too): kubeadm 1.33 asks for pause 3.10 (preloaded as well) and only warns that the runtime's differs."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import cilium_images, kubeadm_images

    versions = kubeadm_images.pinned_versions()
    kubernetes = kubernetes_version or versions["kubernetes"]
    older = kubernetes != versions["kubernetes"]
    if older and _release(kubernetes) >= _release(versions["kubernetes"]):
        raise MachineError(f"the lab builds a site at an older release than the pinned {versions['kubernetes']}: {kubernetes}")
    cache = os.path.abspath(os.path.expanduser(cache_dir))
    binaries = kubernetes_programs(cache, kubernetes)
    upgrade_binaries = {}
    if older:
        upgrade_binaries = kubernetes_programs(cache, versions["kubernetes"])
        kubectl = os.path.join(cache, "bin", f"kubectl-{versions['kubernetes']}")
        if os.path.exists(kubectl):
            upgrade_binaries["kubectl"] = kubectl
    images = kubeadm_images.build_all(cache, log=log, kubernetes_version=kubernetes if older else None)
    if older:
        images.update(kubeadm_images.build_all(cache, log=log))  # what the upgrade to the pinned release runs
    images.update(cilium_images.build(cache, log=log))
    toolbox, archive = kubeadm_images.build_toolbox(cache, log=log)
    images[toolbox] = archive
    chosen = {
        "kuberos_kubernetes_version": kubernetes,
        "kuberos_cgroup_driver": "cgroupfs",
        "kuberos_etcd_image_tag": kubeadm_images.etcd_tag(versions["etcd"]),
        "kuberos_coredns_image_tag": versions["coredns"],
        # nf_conntrack_max is the host's, read-only in a machine's network namespace: kube-proxy must leave it alone
        "kuberos_kube_proxy_conntrack_max_per_core": 0,
        # the machines share this host's disk with everything else on it: the kubelet's default shares (10% and 15%
        # free) would evict every machine's pods at once when the host fills, which says nothing about a machine
        "kuberos_kubelet_eviction_hard": LAB_EVICTION_HARD,
        # the pod network the lab builds from the Go module proxy (build-cilium.sh) and runs: Calico's sources are not
        # all served there (docs/cluster-setup.md)
        "kuberos_cni": "cilium",
        "cilium_version": cilium_images.DEFAULT_VERSION,
        "kuberos_lab_toolbox_image": toolbox,  # the lab's network checks (a busybox image)
        "node_prereqs_kubernetes_binaries": binaries,
        "node_prereqs_image_archives": sorted(images.values()),
        # this machine's root lacks CAP_SYS_RESOURCE, so the machines' root does too: runc may not lower OOM scores
        "node_prereqs_containerd_restrict_oom_score_adj": True,
        "node_prereqs_load_modules": False,  # the machines share this kernel: its modules are not theirs to load
        "node_prereqs_apt_update_cache": False,  # no mirror: the machine image holds the packages
    }
    if older:
        chosen["kuberos_lab_upgrade_binaries"] = upgrade_binaries  # the pinned release's, for the upgrade's nodes
    return chosen


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Lab machines booted with systemd-nspawn (kuberos_lab.machines).")
    sub = parser.add_subparsers(dest="command", required=True)
    up = sub.add_parser("up", help="make and boot the machines; write DIR/inventory.yml and DIR/known_hosts")
    up.add_argument("--state", required=True)
    up.add_argument(
        "--machine",
        action="append",
        default=[],
        metavar="NAME:GROUP[,GROUP...][:NETWORKS]",
        help="NETWORKS: site (default), wan (the lab's internet only: a cloud VM) or site+wan",
    )
    up.add_argument(
        "--route",
        action="append",
        default=[],
        metavar="NETWORK:MACHINE",
        help="this machine routes NETWORK through MACHINE, as the site's router would (a VPN's network)",
    )
    up.add_argument("--wan-subnet", default="", help="the lab's internet, as three octets (default: the subnet's next)")
    up.add_argument("--tag", default="kl", help="prefix of the lab's links, namespaces and cgroups (two letters)")
    up.add_argument("--subnet", default="10.213.0", help="the lab's /24, as its first three octets")
    up.add_argument("--cache-dir", default=os.environ.get("KUBEROS_CACHE_DIR") or "~/.cache/kuberos")
    up.add_argument("--site-vars", action="store_true", help="also build the images kubeadm runs and write DIR/site_vars.yml")
    up.add_argument("--kubernetes-version", help="with --site-vars: an older release than the pinned one (site_vars)")
    up.add_argument(
        "--mirror", action="store_true",
        help="with --site-vars: serve those images from a registry on the lab's bridge, the machines' mirror, instead of "
        "copying every archive to every machine",
    )  # fmt: skip
    root = sub.add_parser("root", help="build (or reuse) the machines' Debian root in the cache; print its folder")
    root.add_argument("--cache-dir", default=os.environ.get("KUBEROS_CACHE_DIR") or "~/.cache/kuberos")
    images = sub.add_parser(
        "site-images", help="build (or reuse) the images the machines' cluster runs (kubeadm's, Cilium's); print them"
    )
    images.add_argument("--cache-dir", default=os.environ.get("KUBEROS_CACHE_DIR") or "~/.cache/kuberos")
    images.add_argument("--kubernetes-version", help="an older release than the pinned one, and the pinned one's (site_vars)")
    down = sub.add_parser("down", help="power off, remove mounts, cgroups, namespaces and links")
    down.add_argument("--state", required=True)
    down.add_argument("--remove", action="store_true", help="also delete the machines' files and the state")
    args = parser.parse_args(argv)
    try:
        if args.command == "root":
            print(build_image(args.cache_dir))
        elif args.command == "site-images":
            chosen = site_vars(args.cache_dir, kubernetes_version=args.kubernetes_version)
            print("\n".join(chosen["node_prereqs_image_archives"]))
        elif args.command == "up":
            specs = []
            for text in args.machine:
                name, _sep, rest = text.partition(":")
                groups, _sep, networks = rest.partition(":")
                specs.append((name, [g for g in groups.split(",") if g], networks or "site"))
            state = os.path.abspath(args.state)
            lab = MachineLab.load(state) if os.path.exists(os.path.join(state, "lab.json")) else MachineLab(
                state, tag=args.tag, subnet=args.subnet, wan_subnet=args.wan_subnet, cache_dir=args.cache_dir)  # fmt: skip
            for route in args.route:
                network, _sep, through = route.partition(":")
                lab.routes[network] = through
            lab.up(specs)
            if args.site_vars:
                import yaml

                chosen = site_vars(args.cache_dir, kubernetes_version=args.kubernetes_version)
                if args.mirror:
                    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import site_lab

                    archives = chosen.pop("node_prereqs_image_archives")
                    chosen["node_prereqs_registry_mirrors"] = site_lab.serve_images(
                        lab.registry(), archives, "", args.cache_dir, app_images=False
                    )
                with open(os.path.join(state, "site_vars.yml"), "w", encoding="utf-8") as handle:
                    yaml.safe_dump(chosen, handle, sort_keys=False)
            print(json.dumps({name: m.address for name, m in lab.machines.items()}))
        else:
            if not os.path.exists(os.path.join(args.state, "lab.json")):
                return 0
            MachineLab.load(os.path.abspath(args.state)).down(remove=args.remove)
    except MachineError as error:
        print(f"lab machines: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
