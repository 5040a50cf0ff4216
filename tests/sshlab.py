"""SSH test hosts for the cluster setup roles: each a network namespace running a real sshd.

A lab host is as close to a separate machine as this one allows without a container runtime:

- its own network namespace (an ``eth0`` on one lab bridge, an address in a subnet that exists only in the
  lab, its own sysctls such as ``net.ipv4.ip_forward``), reached from here through the bridge;
- its own mount and UTS namespaces: a private copy of ``/etc`` (hostname, hosts, ssh, sysctl.d, wireguard,
  kubernetes, apt sources), a private ``/run`` (sshd, wireguard-go's control sockets), ``/root/.ssh``
  (authorized keys) and ``/dev`` (the basic nodes, plus character device nodes for the devices a robot
  carries: ``video0`` is major 81 as video4linux, ``ttyUSB0`` major 188 as USB serial, with no hardware
  behind them), and its hostname;
- a real OpenSSH server (Debian's openssh-server) with its own ed25519 host key, root login by key only.

What the hosts share with this machine: the kernel (no WireGuard module, no netem), the installed programs
and packages under /usr, /var and /opt. So a role run on a lab host changes that host's /etc, /run, /dev,
/root/.ssh and network namespace for real, and nothing of the machine's own.

Used by the tests (``open_ssh_lab``) and, as a command, by the molecule scenarios' create and destroy:

    python tests/sshlab.py up --state DIR --host edge-1:edge --host cloud-1:cloud --host fetch-9:robot:video0,ttyUSB0
    python tests/sshlab.py down --state DIR

``up`` writes ``DIR/inventory.yml`` (groups by role, with the ansible_* connection variables: root, the
lab's admin key, strict host key checking against ``DIR/known_hosts``) and ``DIR/lab.json``. Needs root,
iproute2, util-linux (unshare, nsenter) and openssh-server.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field

import yaml

SSHD = "/usr/sbin/sshd"
DEVICE_NODES = {"video0": (81, 0), "video1": (81, 1), "ttyUSB0": (188, 0), "ttyACM0": (166, 0)}
ROLES = {"robot": "robots", "edge": "edge", "cloud": "cloud", "host": "hosts"}

# Runs inside the host's new mount and UTS namespaces (already inside its network namespace), then
# becomes sshd. $1: the host's state directory, $2: its hostname, $3...: device nodes "name:major:minor".
LAUNCHER = r"""
set -eu
home=$1; name=$2; shift 2
hostname "$name"
mount --make-rprivate /
mount --bind "$home/etc" /etc
mount -t tmpfs -o mode=0755,nosuid,nodev tmpfs /run
mkdir -p /run/sshd /run/wireguard
mount --bind "$home/root-ssh" /root/.ssh
dev="$home/dev"
mount -t tmpfs -o mode=0755,nosuid tmpfs "$dev"
for node in null zero full random urandom tty; do
  touch "$dev/$node"
  mount --bind "/dev/$node" "$dev/$node"
done
if [ -c /dev/net/tun ]; then  # TUN devices: wireguard-go
  mkdir "$dev/net"; touch "$dev/net/tun"; mount --bind /dev/net/tun "$dev/net/tun"
fi
mkdir "$dev/pts" "$dev/shm"
mount -t devpts -o newinstance,ptmxmode=0666,mode=0620 devpts "$dev/pts"
ln -s pts/ptmx "$dev/ptmx"
mount -t tmpfs -o mode=1777,nosuid,nodev tmpfs "$dev/shm"
ln -s /proc/self/fd "$dev/fd"
ln -s /proc/self/fd/0 "$dev/stdin"; ln -s /proc/self/fd/1 "$dev/stdout"; ln -s /proc/self/fd/2 "$dev/stderr"
for spec in "$@"; do
  IFS=: read -r node major minor <<EOF
$spec
EOF
  mknod -m 0660 "$dev/$node" c "$major" "$minor"
done
mount --move "$dev" /dev
exec /usr/sbin/sshd -D -e -f /etc/ssh/sshd_config
"""

SSHD_CONFIG = """\
# sshd of the lab host {name}: root by key only
Port 22
ListenAddress {address}
HostKey /etc/ssh/ssh_host_ed25519_key
PermitRootLogin prohibit-password
PubkeyAuthentication yes
PasswordAuthentication no
KbdInteractiveAuthentication no
UsePAM no
PidFile /run/sshd.pid
AuthorizedKeysFile .ssh/authorized_keys
StrictModes no
PrintMotd no
MaxStartups 50:30:100
Subsystem sftp /usr/lib/openssh/sftp-server
"""


class LabError(RuntimeError):
    """The lab could not be made or used here."""


def run(*command: str, check: bool = True, timeout: float = 30, **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, **kwargs)
    if check and done.returncode != 0:
        raise LabError(f"{' '.join(command)} exited {done.returncode}: {(done.stderr or done.stdout).strip()}")
    return done


def missing_requirements() -> list[str]:
    """What this machine lacks for a lab; empty when a lab can be made."""
    problems = []
    if os.geteuid() != 0:
        problems.append("root (namespaces, mounts)")
    for program in ("ip", "unshare", "nsenter", "ssh-keygen", "ssh"):
        if not shutil.which(program):
            problems.append(program)
    if not os.access(SSHD, os.X_OK):
        problems.append(f"{SSHD} (Debian openssh-server)")
    return problems


@dataclass
class HostSpec:
    name: str
    role: str = "host"  # robot, edge, cloud or host
    devices: list[str] = field(default_factory=list)

    @classmethod
    def parse(cls, text: str) -> HostSpec:
        """``name[:role[:dev1,dev2]]``"""
        parts = text.split(":")
        if not parts[0] or len(parts) > 3:
            raise LabError(f"--host {text!r}: expected name[:role[:device,device]]")
        spec = cls(parts[0], parts[1] if len(parts) > 1 and parts[1] else "host")
        if spec.role not in ROLES:
            raise LabError(f"--host {text!r}: role must be one of {', '.join(ROLES)}")
        spec.devices = [d for d in (parts[2].split(",") if len(parts) > 2 else []) if d]
        unknown = [d for d in spec.devices if d not in DEVICE_NODES]
        if unknown:
            raise LabError(f"--host {text!r}: unknown device {unknown}; known: {', '.join(DEVICE_NODES)}")
        return spec


@dataclass
class LabHost:
    name: str
    role: str
    address: str
    namespace: str
    home: str
    devices: list[str]
    pid: int = 0
    host_key: str = ""  # "ssh-ed25519 AAAA..."


@dataclass
class SSHLab:
    """Hosts on one bridge; ``state`` holds keys, each host's private directories, the inventory."""

    state: str
    suffix: str = field(default_factory=lambda: secrets.token_hex(2))
    subnet: str = ""
    hosts: dict[str, LabHost] = field(default_factory=dict)

    # --- paths ------------------------------------------------------------------------------------------

    @property
    def bridge(self) -> str:
        return f"krlab{self.suffix}"

    @property
    def gateway(self) -> str:
        return f"{self.subnet}.1"

    @property
    def admin_key(self) -> str:
        return os.path.join(self.state, "admin_ed25519")

    @property
    def known_hosts(self) -> str:
        return os.path.join(self.state, "known_hosts")

    @property
    def inventory(self) -> str:
        return os.path.join(self.state, "inventory.yml")

    # --- up and down ------------------------------------------------------------------------------------

    def up(self, specs: list[HostSpec]) -> SSHLab:
        problems = missing_requirements()
        if problems:
            raise LabError("cannot make SSH lab hosts here; missing: " + ", ".join(problems))
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise LabError(f"host names repeat: {names}")
        os.makedirs(self.state, exist_ok=True)
        if not self.subnet:
            self.subnet = free_subnet()
        if not os.path.exists(self.admin_key):
            run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", "kuberos-lab-admin", "-f", self.admin_key)
        self.save()  # from here on, `down` can clean up whatever exists
        run("ip", "link", "add", self.bridge, "type", "bridge")
        run("ip", "addr", "add", f"{self.gateway}/24", "dev", self.bridge)
        run("ip", "link", "set", self.bridge, "up")
        for spec in specs:
            self.add(spec)
        self.write_hosts_files()
        self.save()
        for host in self.hosts.values():
            self.start_sshd(host)
        self.save()
        for host in self.hosts.values():
            wait_for_port(host.address, 22, timeout=15, what=f"sshd of {host.name}", log=self.sshd_log(host))
        self.write_known_hosts()
        self.write_inventory()
        return self

    def add(self, spec: HostSpec) -> LabHost:
        index = len(self.hosts)
        host = LabHost(
            name=spec.name, role=spec.role, address=f"{self.subnet}.{10 + index}",
            namespace=f"krlab-{self.suffix}-{index}", home=os.path.join(self.state, "hosts", spec.name),
            devices=list(spec.devices),
        )  # fmt: skip
        self.hosts[host.name] = host
        port = f"krl{self.suffix}h{index}"
        run("ip", "netns", "add", host.namespace)
        run("ip", "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns", host.namespace)
        run("ip", "link", "set", port, "master", self.bridge, "up")
        run("ip", "-n", host.namespace, "addr", "add", f"{host.address}/24", "dev", "eth0")
        run("ip", "-n", host.namespace, "link", "set", "eth0", "up")
        run("ip", "-n", host.namespace, "link", "set", "lo", "up")
        run("ip", "-n", host.namespace, "route", "add", "default", "via", self.gateway)
        self.make_home(host)
        return host

    def make_home(self, host: LabHost) -> None:
        etc = os.path.join(host.home, "etc")
        if os.path.exists(host.home):
            shutil.rmtree(host.home)
        os.makedirs(os.path.join(host.home, "dev"))
        os.makedirs(os.path.join(host.home, "root-ssh"), mode=0o700)
        # A private copy of /etc, without what belongs to this machine only (its ssh host keys, netns files).
        run("cp", "-a", "--no-preserve=links", "/etc", etc, timeout=120, check=False)
        if not os.path.isdir(os.path.join(etc, "ssh")):
            raise LabError(f"copying /etc to {etc} failed")
        for leftover in os.listdir(os.path.join(etc, "ssh")):
            if leftover.startswith("ssh_host_"):
                os.remove(os.path.join(etc, "ssh", leftover))
        shutil.rmtree(os.path.join(etc, "netns"), ignore_errors=True)
        for directory in ("wireguard", "kubernetes", "sysctl.d", "modules-load.d", "apt/sources.list.d", "apt/keyrings"):
            os.makedirs(os.path.join(etc, directory), exist_ok=True)
        with open(os.path.join(etc, "hostname"), "w", encoding="utf-8") as handle:
            handle.write(host.name + "\n")
        key = os.path.join(etc, "ssh", "ssh_host_ed25519_key")
        run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"root@{host.name}", "-f", key)
        with open(key + ".pub", encoding="utf-8") as handle:
            host.host_key = " ".join(handle.read().split()[:2])
        with open(os.path.join(etc, "ssh", "sshd_config"), "w", encoding="utf-8") as handle:
            handle.write(SSHD_CONFIG.format(name=host.name, address=host.address))
        shutil.rmtree(os.path.join(etc, "ssh", "sshd_config.d"), ignore_errors=True)
        with open(self.admin_key + ".pub", encoding="utf-8") as source:
            admin = source.read()
        authorized = os.path.join(host.home, "root-ssh", "authorized_keys")
        with open(authorized, "w", encoding="utf-8") as handle:
            handle.write(admin)
        os.chmod(authorized, 0o600)

    def write_hosts_files(self) -> None:
        lines = ["127.0.0.1 localhost", "::1 localhost ip6-localhost ip6-loopback"]
        lines += [f"{h.address} {h.name}" for h in self.hosts.values()]
        for host in self.hosts.values():
            with open(os.path.join(host.home, "etc", "hosts"), "w", encoding="utf-8") as handle:
                handle.write("\n".join([*lines, f"127.0.1.1 {host.name}"]) + "\n")

    def sshd_log(self, host: LabHost) -> str:
        return os.path.join(host.home, "sshd.log")

    def start_sshd(self, host: LabHost) -> None:
        os.makedirs("/root/.ssh", mode=0o700, exist_ok=True)  # the mount point of each host's own /root/.ssh
        devices = [f"{d}:{DEVICE_NODES[d][0]}:{DEVICE_NODES[d][1]}" for d in host.devices]
        command = [
            "ip", "netns", "exec", host.namespace, "unshare", "--mount", "--uts", "--propagation", "private",
            "bash", "-c", LAUNCHER, "launcher", host.home, host.name, *devices,
        ]  # fmt: skip
        with open(self.sshd_log(host), "ab") as log:
            process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True)
        host.pid = process.pid

    def write_known_hosts(self) -> None:
        with open(self.known_hosts, "w", encoding="utf-8") as handle:
            for host in self.hosts.values():
                handle.write(f"{host.address} {host.host_key}\n")

    def connection_vars(self) -> dict:
        return {
            "ansible_user": "root",
            "ansible_ssh_private_key_file": self.admin_key,
            "ansible_ssh_common_args": f"-o UserKnownHostsFile={self.known_hosts} -o StrictHostKeyChecking=yes",
            "ansible_python_interpreter": "/usr/bin/python3",
        }

    def write_inventory(self) -> None:
        children: dict = {}
        for host in self.hosts.values():
            group = children.setdefault(ROLES[host.role], {"hosts": {}})
            group["hosts"][host.name] = {"ansible_host": host.address, "kuberos_address": host.address}
        with open(self.inventory, "w", encoding="utf-8") as handle:
            yaml.safe_dump({"all": {"vars": self.connection_vars(), "children": children}}, handle, sort_keys=False)

    def save(self) -> None:
        with open(os.path.join(self.state, "lab.json"), "w", encoding="utf-8") as handle:
            json.dump(asdict(self), handle, indent=1)

    @classmethod
    def load(cls, state: str) -> SSHLab:
        with open(os.path.join(state, "lab.json"), encoding="utf-8") as handle:
            data = json.load(handle)
        hosts = {name: LabHost(**values) for name, values in data.pop("hosts").items()}
        return cls(**data, hosts=hosts)

    def down(self) -> None:
        """Stop every sshd (and what runs in the hosts' namespaces), remove the namespaces and the bridge."""
        for host in self.hosts.values():
            if host.pid:
                try:
                    os.killpg(host.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for host in self.hosts.values():
            # Whatever a role started on the host (wireguard-go, ...) lives in its network namespace.
            for pid in run("ip", "netns", "pids", host.namespace, check=False).stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            run("ip", "netns", "delete", host.namespace, check=False)
        run("ip", "link", "delete", self.bridge, check=False)

    # --- using the hosts --------------------------------------------------------------------------------

    def exec(self, name: str, *command: str, check: bool = True, timeout: float = 30) -> subprocess.CompletedProcess:
        """Run a command on a host as its sshd sees the world (its network, mounts and hostname)."""
        host = self.hosts[name]
        sshd = sshd_pid(host.pid)
        return run("nsenter", "-t", str(sshd), "-n", "-m", "-u", *command, check=check, timeout=timeout)

    def ssh(self, name: str, *command: str, check: bool = True, timeout: float = 30) -> subprocess.CompletedProcess:
        """Run a command on a host over SSH, as Ansible would reach it."""
        host = self.hosts[name]
        options = ["-o", f"UserKnownHostsFile={self.known_hosts}", "-o", "StrictHostKeyChecking=yes", "-o", "BatchMode=yes"]
        return run("ssh", *options, "-i", self.admin_key, f"root@{host.address}", *command, check=check, timeout=timeout)

    def replace_host_key(self, name: str, timeout: float = 15) -> str:
        """Give a host a new ed25519 host key (as a reinstall, or an impostor, would), reload its sshd, wait until
        it presents the new key; the lab's own known_hosts follows. Returns the new ``ssh-ed25519 AAAA...``."""
        host = self.hosts[name]
        key = os.path.join(host.home, "etc", "ssh", "ssh_host_ed25519_key")
        for old in (key, key + ".pub"):
            os.remove(old)
        run("ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", f"root@{host.name}", "-f", key)
        with open(key + ".pub", encoding="utf-8") as handle:
            host.host_key = " ".join(handle.read().split()[:2])
        os.kill(sshd_pid(host.pid), signal.SIGHUP)  # sshd re-executes itself and reads its host keys again
        deadline = time.monotonic() + timeout
        while True:
            scan = run("ssh-keyscan", "-T", "2", "-t", "ed25519", host.address, check=False).stdout
            if host.host_key in scan:
                break
            if time.monotonic() > deadline:
                raise LabError(f"sshd of {name} did not present its new host key within {timeout:.0f} s")
            time.sleep(0.2)
        self.write_known_hosts()
        self.save()
        return host.host_key

    def path(self, name: str, inside: str) -> str:
        """Where a path of a host's private /etc or /root/.ssh is, seen from this machine."""
        home = self.hosts[name].home
        for prefix, local in (("/etc/", "etc/"), ("/root/.ssh/", "root-ssh/")):
            if inside.startswith(prefix):
                return os.path.join(home, local + inside[len(prefix) :])
        raise LabError(f"{inside} is not in a lab host's private directories")


def sshd_pid(launcher: int) -> int:
    """The launcher execs sshd, so its pid is sshd's; check it is still alive."""
    try:
        os.kill(launcher, 0)
    except ProcessLookupError as error:
        raise LabError(f"the lab host's sshd (pid {launcher}) is not running") from error
    return launcher


def free_subnet() -> str:
    """A 10.23x.y.0/24 that no interface of this machine uses."""
    used = run("ip", "-o", "-4", "addr", "show").stdout
    for _ in range(50):
        subnet = f"10.{230 + secrets.randbelow(10)}.{secrets.randbelow(256)}"
        if f" {subnet}." not in used:
            return subnet
    raise LabError("no free 10.23x.y.0/24 subnet found")


def wait_for_port(address: str, port: int, timeout: float, what: str, log: str = "") -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((address, port), timeout=1):
                return
        except OSError as error:
            if time.monotonic() > deadline:
                tail = ""
                if log and os.path.exists(log):
                    with open(log, encoding="utf-8", errors="replace") as handle:
                        tail = "\n" + handle.read()[-2000:]
                raise LabError(f"{what} did not answer on {address}:{port} within {timeout:.0f} s: {error}{tail}") from error
            time.sleep(0.1)


def open_ssh_lab(request, tmp_path_factory, specs: list[HostSpec]) -> SSHLab:
    """A lab for a test module or session: skipped where it cannot be made (not root, no sshd), torn down after."""
    import pytest

    problems = missing_requirements()
    if problems:
        if os.environ.get("CI"):
            pytest.fail("SSH lab hosts are needed in CI; missing: " + ", ".join(problems))
        pytest.skip("SSH lab hosts need: " + ", ".join(problems))
    lab = SSHLab(state=str(tmp_path_factory.mktemp("sshlab")))
    request.addfinalizer(lab.down)
    lab.up(specs)
    return lab


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="action", required=True)
    up = sub.add_parser("up", help="make the hosts and start their sshd; writes STATE/inventory.yml")
    up.add_argument("--state", required=True, help="directory for keys, the hosts' private directories, the inventory")
    up.add_argument("--host", action="append", required=True, help="name[:role[:device,device]] (role: robot, edge, cloud, host)")
    down = sub.add_parser("down", help="stop the hosts and remove their namespaces")
    down.add_argument("--state", required=True)
    down.add_argument("--remove", action="store_true", help="also remove the state directory")
    args = parser.parse_args(argv)
    try:
        if args.action == "up":
            lab = SSHLab(state=os.path.abspath(args.state))
            try:
                lab.up([HostSpec.parse(h) for h in args.host])
            except Exception:
                lab.down()
                raise
            for host in lab.hosts.values():
                print(f"{host.name:16} {host.role:6} {host.address:15} ns={host.namespace} sshd pid={host.pid}")
            print(f"inventory: {lab.inventory}")
        else:
            if os.path.exists(os.path.join(args.state, "lab.json")):
                SSHLab.load(args.state).down()
            if args.remove:
                shutil.rmtree(args.state, ignore_errors=True)
    except LabError as error:
        print(f"sshlab: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
