"""Three stand-in control planes on this machine, for running the control plane's day-2 playbooks (etcd_restore.yml,
certificates.yml) for real without lab machines.

Each control plane is an inventory host reached by Ansible's local connection, with a root folder of its own
(``kubeadm_init_config_dir`` points into it) that holds what kubeadm made: `kubeadm init phase certs all` and
`kubeconfig all` run for real (kubeadm v1.34.4) with the host's stand-in address among the certificates' names. A
stand-in kubelet (a thread) watches each host's ``manifests`` folder as the kubelet watches its static pods: while
``etcd.yaml`` is there it runs a real etcd v3.5.35 member with the manifest's flags (peer TLS with kubeadm's etcd
certificates, a three-member cluster on 127.0.0.31-33), while ``kube-apiserver.yaml`` is there it serves the API
server's ``/readyz`` on the host's address with kubeadm's apiserver certificate (read anew at each start, as a
restarted API server does), ready when its etcd member is; etcd's ``/health`` answers on 127.0.0.1:2381 and the
controller manager's and scheduler's ``/healthz`` on 127.0.0.1:10257 and :10259, as on a control plane.

What differs from a site, in ``bin/`` ahead of PATH: ``ctr`` runs the etcdutl of the cache with the arguments that
follow ``etcdutl`` (a site runs it from the etcd image), ``pgrep`` answers "gone" (the members here are not named
etcd), and ``kubeadm-<host>`` runs the real kubeadm in that host's root (``--rootfs``) with its configuration file
(a site's kubeadm reads the cluster's). ``become`` is off: this machine's user is root.
"""

from __future__ import annotations

import http.server
import os
import shutil
import ssl
import subprocess
import threading
import time
import urllib.request

import yaml
from helpers import ROOT, venv_tool

HOSTS = {"edge-a": "127.0.0.31", "edge-b": "127.0.0.32", "edge-c": "127.0.0.33"}
INVENTORY_NAMES = {host: f"{host}.site.example" for host in HOSTS}
# What kubeadm shares between the control planes of one cluster (kubeadm init phase upload-certs' list).
SHARED_PKI = ("ca.crt", "ca.key", "sa.key", "sa.pub", "front-proxy-ca.crt", "front-proxy-ca.key", "etcd/ca.crt", "etcd/ca.key")

CTR = """#!/bin/bash
# Stand-in for ctr run ... IMAGE ID etcdutl ARGS: the cache's etcdutl with ARGS. FAIL_RESTORE_ON=<member> fails its restore.
echo "ctr $*" >> "{folder}/ctr.log"
args=("$@"); for i in "${{!args[@]}}"; do [[ ${{args[$i]}} == etcdutl ]] && {{ start=$((i+1)); break; }}; done
if [[ -n ${{FAIL_RESTORE_ON:-}} && "$*" == *"restore"*"--name ${{FAIL_RESTORE_ON}} "* ]]; then
  echo "simulated failure" >&2; exit 3
fi
exec "{etcdutl}" "${{args[@]:$start}}"
"""
PGREP = """#!/bin/bash
# Stand-in for pgrep -x NAME: the stand-in members are not named etcd; the stand-in kubelet stops them by itself.
echo "pgrep $*" >> "{folder}/pgrep.log"
exit 1
"""
KUBEADM = """#!/bin/bash
# Stand-in for kubeadm on {host}: the real kubeadm in that host's root, with its configuration file.
echo "{host} $*" >> "{folder}/kubeadm.log"
exec "{kubeadm}" "$@" --rootfs "{root}" --config /kubeadm.yaml
"""


def _config(host: str, address: str) -> str:
    """The host's kubeadm configuration: its stand-in address in the API server's and etcd's certificates (kubeadm
    refuses a loopback advertise address: a documentation address stands there)."""
    return f"""apiVersion: kubeadm.k8s.io/v1beta4
kind: InitConfiguration
localAPIEndpoint:
  advertiseAddress: 192.0.2.{address.rsplit(".", 1)[1]}
  bindPort: 6443
nodeRegistration:
  name: {host}
---
apiVersion: kubeadm.k8s.io/v1beta4
kind: ClusterConfiguration
kubernetesVersion: v1.34.4
controlPlaneEndpoint: 127.0.0.1:6443
certificatesDir: /etc/kubernetes/pki
apiServer:
  certSANs: [{address}]
etcd:
  local:
    serverCertSANs: [{address}]
    peerCertSANs: [{", ".join(HOSTS.values())}]
"""


class _Handler(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        ok = self.server.ready()
        self.send_response(200 if ok else 503)
        self.send_header("Content-Type", "text/plain; charset=utf-8")  # as etcd 3.5 answers /health
        self.end_headers()
        self.wfile.write(self.server.body(ok))

    def log_message(self, *_args):
        pass


class StandinSite:
    def __init__(self, folder: str, programs: dict):
        self.folder, self.programs = str(folder), programs
        self.members: dict[str, subprocess.Popen] = {}
        self.apiservers: dict[str, http.server.HTTPServer] = {}
        self.events: list[tuple[str, str]] = []  # (what, host) in order: the kubelet's starts and stops
        self._servers: list[http.server.HTTPServer] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._kubelet, name="standin-kubelet", daemon=True)
        self._logs: list = []

    # -- paths ---------------------------------------------------------------------------------------------------
    def root(self, host: str) -> str:
        return os.path.join(self.folder, host)

    def config_dir(self, host: str) -> str:
        return os.path.join(self.root(host), "etc", "kubernetes")

    def data_dir(self, host: str) -> str:
        return os.path.join(self.root(host), "var", "lib", "etcd")

    @property
    def bin(self) -> str:
        return os.path.join(self.folder, "bin")

    @property
    def inventory(self) -> str:
        return os.path.join(self.folder, "inventory.yml")

    # -- set-up --------------------------------------------------------------------------------------------------
    def setup(self) -> StandinSite:
        os.makedirs(self.bin, exist_ok=True)
        self._script("ctr", CTR.format(folder=self.folder, etcdutl=self.programs["etcdutl"]))
        self._script("pgrep", PGREP.format(folder=self.folder))
        hosts = {}
        cluster = ",".join(f"{h}=https://{a}:2380" for h, a in HOSTS.items())
        for host, address in HOSTS.items():
            root = self.root(host)
            os.makedirs(os.path.join(self.config_dir(host), "manifests"), exist_ok=True)
            os.makedirs(self.data_dir(host), exist_ok=True)
            with open(os.path.join(root, "kubeadm.yaml"), "w", encoding="utf-8") as handle:
                handle.write(_config(host, address))
            if host != next(iter(HOSTS)):  # one cluster: its authorities shared, as a joining control plane gets them
                first = os.path.join(self.config_dir(next(iter(HOSTS))), "pki")
                for name in SHARED_PKI:
                    os.makedirs(os.path.dirname(os.path.join(self.config_dir(host), "pki", name)), exist_ok=True)
                    shutil.copy2(os.path.join(first, name), os.path.join(self.config_dir(host), "pki", name))
            for phase in ("certs", "kubeconfig"):
                done = subprocess.run([self.programs["kubeadm"], "init", "phase", phase, "all", "--rootfs", root,
                                       "--config", "/kubeadm.yaml"], capture_output=True, text=True, timeout=120)  # fmt: skip
                assert done.returncode == 0, f"kubeadm init phase {phase} all on {host}: {done.stderr[-2000:]}"
            self._script(
                f"kubeadm-{host}", KUBEADM.format(host=host, folder=self.folder, kubeadm=self.programs["kubeadm"], root=root)
            )
            pki = os.path.join(self.config_dir(host), "pki", "etcd")
            command = [
                "etcd", f"--name={host}", f"--data-dir={self.data_dir(host)}",
                f"--initial-advertise-peer-urls=https://{address}:2380", f"--listen-peer-urls=https://{address}:2380",
                f"--listen-client-urls=http://{address}:2379", f"--advertise-client-urls=http://{address}:2379",
                f"--initial-cluster={cluster}", f"--peer-cert-file={pki}/peer.crt", f"--peer-key-file={pki}/peer.key",
                f"--peer-trusted-ca-file={pki}/ca.crt", "--peer-client-cert-auth=true",
                f"--listen-metrics-urls=http://{address}:2381", "--snapshot-count=10000",
            ]  # fmt: skip
            etcd = {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": "etcd", "namespace": "kube-system"},
                    "spec": {"containers": [{"name": "etcd", "image": "registry.k8s.io/etcd:3.5.35-0", "command": command}],
                             "volumes": [{"name": "etcd-data", "hostPath": {"path": self.data_dir(host)}}]}}  # fmt: skip
            self._manifest(host, "etcd", etcd)
            for other in ("kube-apiserver", "kube-controller-manager", "kube-scheduler"):
                self._manifest(host, other, {"apiVersion": "v1", "kind": "Pod", "metadata": {"name": other}})
            hosts[INVENTORY_NAMES[host]] = {
                "kuberos_node_name": host, "kuberos_address": address, "kubeadm_init_config_dir": self.config_dir(host),
                "certificates_kubeadm_path": os.path.join(self.bin, f"kubeadm-{host}"),
            }  # fmt: skip
        inventory = {"all": {"vars": {"ansible_connection": "local", "ansible_python_interpreter": venv_tool("python")},
                             "children": {"edge": {"children": {"control_plane": {"hosts": hosts}}}}}}  # fmt: skip
        with open(self.inventory, "w", encoding="utf-8") as handle:
            yaml.safe_dump(inventory, handle)
        return self

    def _script(self, name: str, text: str) -> None:
        path = os.path.join(self.bin, name)
        with open(path, "w", encoding="utf-8") as handle:
            handle.write(text)
        os.chmod(path, 0o755)

    def _manifest(self, host: str, name: str, body: dict) -> None:
        with open(os.path.join(self.config_dir(host), "manifests", f"{name}.yaml"), "w", encoding="utf-8") as handle:
            yaml.safe_dump(body, handle)

    # -- the stand-in kubelet ------------------------------------------------------------------------------------
    def member_healthy(self, host: str) -> bool:
        try:
            with urllib.request.urlopen(f"http://{HOSTS[host]}:2381/health", timeout=1) as response:
                return b'"health":"true"' in response.read().replace(b" ", b"")
        except Exception:  # not up, refused, no leader
            return False

    def _serve(self, address: str, port: int, ready, body, certificate=None) -> http.server.HTTPServer:
        server = http.server.ThreadingHTTPServer((address, port), _Handler)
        server.ready, server.body = ready, body
        if certificate:
            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            context.load_cert_chain(*certificate)
            server.socket = context.wrap_socket(server.socket, server_side=True)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        return server

    def _kubelet(self) -> None:
        while not self._stop.is_set():
            for host, address in HOSTS.items():
                manifests = os.path.join(self.config_dir(host), "manifests")
                etcd = os.path.join(manifests, "etcd.yaml")
                if os.path.exists(etcd) and host not in self.members:
                    with open(etcd, encoding="utf-8") as handle:
                        command = yaml.safe_load(handle)["spec"]["containers"][0]["command"]
                    self._logs.append(open(os.path.join(self.folder, f"etcd-{host}.log"), "a", encoding="utf-8"))
                    self.members[host] = subprocess.Popen([self.programs["etcd"], *command[1:]], stdout=self._logs[-1],
                                                          stderr=subprocess.STDOUT)  # fmt: skip
                    self.events.append(("start etcd", host))
                elif not os.path.exists(etcd) and host in self.members:
                    self._end(self.members.pop(host))
                    self.events.append(("stop etcd", host))
                apiserver = os.path.exists(os.path.join(manifests, "kube-apiserver.yaml"))
                if apiserver and host not in self.apiservers:
                    pki = os.path.join(self.config_dir(host), "pki")
                    ready = lambda h=host: self.member_healthy(h)  # noqa: E731
                    body = lambda ok: b"ok" if ok else b"etcd"  # noqa: E731
                    self.apiservers[host] = self._serve(
                        address, 6443, ready, body, (f"{pki}/apiserver.crt", f"{pki}/apiserver.key")
                    )
                    self.events.append(("start kube-apiserver", host))
                elif not apiserver and host in self.apiservers:
                    server = self.apiservers.pop(host)
                    server.shutdown()
                    server.server_close()
                    self.events.append(("stop kube-apiserver", host))
            self._stop.wait(0.3)

    @staticmethod
    def _end(process: subprocess.Popen) -> None:
        process.terminate()
        try:
            process.wait(20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)

    def start(self, timeout: float = 60) -> StandinSite:
        pki = os.path.join(self.config_dir("edge-a"), "pki")
        every = lambda: all(self.member_healthy(h) for h in self.members)  # noqa: E731
        self._servers.append(
            self._serve("127.0.0.1", 2381, every, lambda ok: b'{"health":"%s","reason":""}' % (b"true" if ok else b"false"))
        )
        for port in (10257, 10259):  # their own serving certificates are self-signed on a site too: any will do
            self._servers.append(
                self._serve("127.0.0.1", port, lambda: True, lambda ok: b"ok", (f"{pki}/apiserver.crt", f"{pki}/apiserver.key"))
            )
        self._thread.start()
        return self.wait_healthy(timeout)

    def wait_healthy(self, timeout: float = 60) -> StandinSite:
        """Until every member runs and answers its health check (bounded)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if len(self.members) == len(HOSTS) and all(self.member_healthy(h) for h in HOSTS):
                return self
            time.sleep(0.5)
        raise AssertionError(f"the stand-in etcd members did not become healthy within {timeout:.0f} s")

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10)
        for process in self.members.values():
            self._end(process)
        for server in [*self.apiservers.values(), *self._servers]:
            server.shutdown()
            server.server_close()
        for log in self._logs:
            log.close()
        self.members, self.apiservers, self._servers, self._logs = {}, {}, [], []

    # -- use -----------------------------------------------------------------------------------------------------
    def ctl(self, *argv: str, check: bool = True) -> subprocess.CompletedProcess:
        command = [self.programs["etcdctl"], f"--endpoints=http://{HOSTS['edge-a']}:2379", "--dial-timeout=2s",
                   "--command-timeout=10s", *argv]  # fmt: skip
        done = subprocess.run(command, capture_output=True, text=True, timeout=60, check=False)
        if check:
            assert done.returncode == 0, f"etcdctl {' '.join(argv)}: {done.stderr[-1500:]}"
        return done

    def playbook(self, name: str, *extra: str, env: dict | None = None, timeout: float = 900) -> subprocess.CompletedProcess:
        """playbooks/<name> against the stand-ins, the stand-in programs ahead of PATH, become off."""
        environment = {**os.environ, **(env or {}), "PATH": f"{self.bin}:{os.environ.get('PATH', '')}",
                       "ANSIBLE_CONFIG": os.path.join(ROOT, "ansible.cfg"), "ANSIBLE_NOCOLOR": "1",
                       "ANSIBLE_FORCE_COLOR": "0"}  # fmt: skip
        command = [venv_tool("ansible-playbook"), f"playbooks/{name}", "-i", self.inventory, "-e", "ansible_become=false", *extra]
        return subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, text=True, timeout=timeout, check=False)
