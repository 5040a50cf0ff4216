"""The control planes' virtual IP held by real keepalived daemons with the role's own configuration and health check.

Three network namespaces on one bridge stand in for three control planes; each runs keepalived (the Debian package,
scripts/setup.sh installs it) with keepalived.conf and kuberos-apiserver-check rendered from the control_plane_vip
role's templates, and a small HTTPS server on its loopback as its API server's /livez. A thread asks every 0.1 s which
namespaces hold the address. The site's days, in order:

- a new site: only the first control plane runs keepalived (the others wait for their API servers) and, being no node
  yet, takes the address for kubeadm init;
- the other two join and start keepalived: the first keeps the address;
- the holder's API server dies: the address goes to the next control plane by priority, never to two;
- the first control plane's API server comes back (as a rebuilt first control plane does): the holder keeps it -
  keepalived's nopreempt; the old configuration (a live API server's weight, preemption) gave it back here;
- the holder is powered off: the address goes to the highest-priority control plane left.

Never two holders at any sample. Traffic stays on the bridge the test creates (no address, no uplink).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import threading
import time

import jinja2
import pytest
import yaml
from helpers import ROOT
from netlab import SUBNET, Process, open_lab, spawn
from sshlab import run

pytestmark = pytest.mark.host  # network namespaces, a bridge and keepalived daemons on this machine

ROLE = os.path.join(ROOT, "roles", "control_plane_vip")
VIP = f"{SUBNET}.100"
NAMES = ("edge-a", "edge-b", "edge-c")  # control_plane_vip_hosts, highest priority first
CHECK_INTERVAL = 1  # control_plane_vip_check_interval: control_plane_vip_check_fall missed checks give the address away
with open(os.path.join(ROLE, "defaults", "main.yml"), encoding="utf-8") as _handle:
    DEFAULTS = yaml.safe_load(_handle)  # the check's timeout and fall as a site gets them
# An API server's /livez on the namespace's loopback (the health check asks https://127.0.0.1:<port>/livez).
LIVEZ = """
import http.server, ssl, sys
class Livez(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        self.send_response(200 if self.path == "/livez" else 404); self.end_headers(); self.wfile.write(b"ok")
    def log_message(self, *args):
        pass
server = http.server.HTTPServer(("127.0.0.1", int(sys.argv[1])), Livez)
context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER); context.load_cert_chain(sys.argv[2], sys.argv[3])
server.socket = context.wrap_socket(server.socket, server_side=True)
print("serving", flush=True)
server.serve_forever()
"""
PORT = 16443


def _keepalived() -> str:
    path = shutil.which("keepalived") or ("/usr/sbin/keepalived" if os.access("/usr/sbin/keepalived", os.X_OK) else "")
    if not path:
        message = "keepalived is not installed (scripts/setup.sh installs it with apt as root)"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


def _priority(name: str) -> int:
    """The priority the role gives ``name``: its own expression (tasks/main.yml), rendered for that host."""
    with open(os.path.join(ROLE, "tasks", "main.yml"), encoding="utf-8") as handle:
        tasks = yaml.safe_load(handle)
    expression = next(t for t in tasks if "control_plane_vip__priority" in t.get("ansible.builtin.set_fact", {}))
    source = expression["ansible.builtin.set_fact"]["control_plane_vip__priority"]
    return int(jinja2.Template(source).render(control_plane_vip_hosts=list(NAMES), inventory_hostname=name))


def _render(template: str, **values) -> str:
    with open(os.path.join(ROLE, "templates", template), encoding="utf-8") as handle:
        return jinja2.Environment(undefined=jinja2.StrictUndefined).from_string(handle.read()).render(**values)


class ControlPlane:
    """One namespace's keepalived, its health check and its stand-in API server, in a root-only folder (keepalived's
    script security refuses a script on a path that anyone but root may write to)."""

    def __init__(self, lab, name: str, folder: str, addresses: dict[str, str], logs: str):
        self.lab, self.name, self.folder, self.logs = lab, name, folder, logs
        self.namespace, self.address = lab.namespaces[name], addresses[name]
        self.kubelet_conf = os.path.join(folder, "kubelet.conf")
        self.keepalived: Process | None = None
        self.apiserver: Process | None = None
        self.powered = True
        values = {
            "ansible_managed": "rendered by tests/integration/test_control_plane_vip.py",
            "inventory_hostname": name,
            "control_plane_vip_config_dir": folder,
            "control_plane_vip_check_interval": CHECK_INTERVAL,
            "control_plane_vip_check_timeout": DEFAULTS["control_plane_vip_check_timeout"],
            "control_plane_vip_check_fall": DEFAULTS["control_plane_vip_check_fall"],
            "control_plane_vip_router_id": 51,
            "control_plane_vip__priority": _priority(name),
            "control_plane_vip__interface": "eth0",
            "control_plane_vip__auth_pass": "kuberos1",
            "control_plane_vip_host_address": self.address,
            "control_plane_vip__peers": [a for n, a in addresses.items() if n != name],
            "control_plane_vip_address": VIP,
            "control_plane_vip_apiserver_port": PORT,
            "control_plane_vip_kubelet_conf": self.kubelet_conf,
        }
        for template, target, mode in (
            ("keepalived.conf.j2", "keepalived.conf", 0o600),
            ("kuberos-apiserver-check.j2", "kuberos-apiserver-check", 0o700),
        ):
            path = os.path.join(folder, target)
            with open(path, "w", encoding="utf-8") as handle:
                handle.write(_render(template, **values))
            os.chmod(path, mode)

    def _in_namespace(self, command: list[str]) -> list[str]:
        return [shutil.which("ip"), "netns", "exec", self.namespace, *command]

    def start_keepalived(self, program: str) -> None:
        pids = [os.path.join(self.folder, f"{kind}.pid") for kind in ("keepalived", "vrrp", "checkers")]
        command = [program, "--dont-fork", "--log-console", "--log-detail", "--vrrp", "--use-file",
                   os.path.join(self.folder, "keepalived.conf"), "--pid", pids[0], "--vrrp_pid", pids[1],
                   "--checkers_pid", pids[2]]  # fmt: skip
        self.keepalived = spawn(f"keepalived-{self.name}", self._in_namespace(command), dict(os.environ), self.logs)

    def join(self, certificate: str, key: str) -> None:
        """kubeadm's effect as the health check sees it: a kubelet.conf, and an API server that answers /livez."""
        with open(self.kubelet_conf, "w", encoding="utf-8") as handle:
            handle.write("# stands in for the kubelet's kubeconfig\n")
        self.start_apiserver(certificate, key)

    def start_apiserver(self, certificate: str, key: str) -> None:
        command = self._in_namespace([sys.executable, "-c", LIVEZ, str(PORT), certificate, key])
        self.apiserver = spawn(f"apiserver-{self.name}", command, dict(os.environ), self.logs)
        deadline = time.monotonic() + 15
        while "serving" not in self.apiserver.output() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert "serving" in self.apiserver.output(), self.apiserver.tail()

    def stop_apiserver(self) -> None:
        if self.apiserver:
            self.apiserver.kill()

    def power_off(self) -> None:
        """Cut off and stopped dead: no priority-0 advert, the address left on its interface (not counted)."""
        self.powered = False
        self.lab.set_connected(self.name, False)
        for process in (self.keepalived, self.apiserver):
            if process:
                process.kill(9)

    def holds(self) -> bool:
        shown = run("ip", "-n", self.namespace, "-o", "-4", "addr", "show", "to", f"{VIP}/32", check=False)
        return self.powered and bool(shown.stdout.strip())

    def log(self) -> str:
        return self.keepalived.tail(25) if self.keepalived else ""


class Holders(threading.Thread):
    """Which control planes hold the address, every 0.1 s: the most at once, and each change of holder with its time."""

    def __init__(self, planes: list[ControlPlane]):
        super().__init__(daemon=True)
        self.planes, self.samples, self.most, self.changes = planes, 0, 0, []
        self.current: tuple[str, ...] = ()
        self.started_at = time.monotonic()
        self._stopping = threading.Event()

    def run(self) -> None:
        while not self._stopping.is_set() and time.monotonic() - self.started_at < 300:
            held = tuple(p.name for p in self.planes if p.holds())
            self.samples += 1
            self.most = max(self.most, len(held))
            if held != self.current:
                self.changes.append((round(time.monotonic() - self.started_at, 1), held))
                self.current = held
            self._stopping.wait(0.1)

    def stop(self) -> None:
        self._stopping.set()
        self.join(5)

    def wait_for(self, holders: tuple[str, ...], timeout: float, planes) -> float:
        start = time.monotonic()
        while time.monotonic() - start < timeout:
            if self.current == holders:
                return time.monotonic() - start
            time.sleep(0.1)
        pytest.fail(f"holders {self.current}, not {holders}, after {timeout:.0f} s; changes {self.changes}\n"
                    + "\n".join(p.log() for p in planes), pytrace=False)  # fmt: skip

    def stays(self, holders: tuple[str, ...], seconds: float, planes) -> None:
        changes = len(self.changes)
        time.sleep(seconds)
        assert self.current == holders and len(self.changes) == changes, (
            f"expected {holders} to keep the address for {seconds:.0f} s; changes {self.changes}\n"
            + "\n".join(p.log() for p in planes)
        )


@pytest.fixture()
def control_planes(request):
    program = _keepalived()
    lab = open_lab(request, NAMES[0])
    for name in NAMES[1:]:
        lab.add(name)
    folder = tempfile.mkdtemp(prefix="kuberos-vip-", dir="/run")  # root-owned path: keepalived's script security
    request.addfinalizer(lambda: shutil.rmtree(folder, ignore_errors=True))
    os.chmod(folder, 0o700)
    certificate, key = os.path.join(folder, "tls.crt"), os.path.join(folder, "tls.key")
    run("openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-days", "1",
        "-subj", "/CN=kube-apiserver", "-keyout", key, "-out", certificate)  # fmt: skip
    planes = []
    for name in NAMES:
        os.makedirs(os.path.join(folder, name), mode=0o700)
        planes.append(ControlPlane(lab, name, os.path.join(folder, name), dict(lab.addresses), folder))

    def close():
        for plane in planes:
            for process in (plane.keepalived, plane.apiserver):
                if process:
                    process.kill()

    request.addfinalizer(close)
    return program, planes, (certificate, key)


def test_one_holder_at_any_time_and_a_control_plane_that_comes_back_never_takes_the_address(control_planes):
    program, planes, tls = control_planes
    a, b, c = planes
    assert [_priority(p.name) for p in planes] == sorted((_priority(p.name) for p in planes), reverse=True)
    holders = Holders(planes)
    holders.start()
    try:
        # A new site: keepalived on the first control plane only; no node yet, so its check passes: it takes the address.
        a.start_keepalived(program)
        holders.wait_for(("edge-a",), 20, planes)
        a.join(*tls)  # kubeadm init
        # The others join, then start keepalived (site.yml's play after the join): the first keeps the address.
        for plane in (b, c):
            plane.join(*tls)
            plane.start_keepalived(program)
        holders.stays(("edge-a",), 6, planes)
        # The holder's API server dies: FAULT, the address to the next by priority.
        a.stop_apiserver()
        moved = holders.wait_for(("edge-b",), 20, planes)
        # It comes back, as a rebuilt first control plane does with the highest priority: the holder keeps the address.
        a.start_apiserver(*tls)
        holders.stays(("edge-b",), 8, planes)
        # The holder is powered off: the highest-priority control plane left takes it.
        b.power_off()
        holders.wait_for(("edge-a",), 20, planes)
        holders.stays(("edge-a",), 3, planes)
    finally:
        holders.stop()
    assert holders.samples >= 150 and holders.most == 1, (holders.samples, holders.changes)
    assert moved < 3 * CHECK_INTERVAL + 5, (moved, holders.changes)
