"""A real Kubernetes control plane on this machine: etcd, kube-apiserver, kube-controller-manager,
kube-scheduler and kwok (simulated nodes), each a background process with a pid file and a log.

No Ansible and no Kubernetes client here: the ``local_cluster`` module and the test fixtures both
drive ``LocalControlPlane``. Certificates come from ``cryptography``; serving is TLS only, clients
authenticate with certificates, anonymous access is off.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import urllib.error
from dataclasses import dataclass, field

from ansible.module_utils.urls import open_url

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.background_process import alive
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import pki

COMPONENTS = ("etcd", "kube-apiserver", "kube-controller-manager", "kube-scheduler", "kwok")
SERVICE_CIDR = "10.96.0.0/16"


@dataclass
class Ports:
    apiserver: int = 16443
    etcd_client: int = 12379
    etcd_peer: int = 12380
    controller_manager: int = 10257 + 6000
    scheduler: int = 10259 + 6000
    kwok: int = 10247 + 6000


@dataclass
class LocalControlPlane:
    state_dir: str
    binaries: dict  # component -> path
    ports: Ports = field(default_factory=Ports)
    kwok_stages: list = field(default_factory=list)  # stage configuration files for kwok
    # The address of the `kubernetes` Service's endpoint: pods of real nodes reach the API server there (the real
    # nodes' relay on their management bridge); 127.0.0.1 when every node is kwok's.
    advertise_address: str = "127.0.0.1"
    # How long a pod that does not say otherwise stays on a node that is unreachable or not ready before it is
    # evicted (the API server's default tolerations; Kubernetes' default is 300 s). Tests shorten it.
    unreachable_toleration_s: int = 300
    log: list = field(default_factory=list)  # what was done, for the caller to report
    _children: dict = field(default_factory=dict, repr=False)  # processes started by this object

    # -- paths -----------------------------------------------------------------------------------
    def path(self, *parts: str) -> str:
        return os.path.join(self.state_dir, *parts)

    @property
    def kubeconfig(self) -> str:
        return self.path("kubeconfig")

    @property
    def server(self) -> str:
        return f"https://127.0.0.1:{self.ports.apiserver}"

    # -- certificates ----------------------------------------------------------------------------
    def issue_certificate(self, name: str, cn: str, org: str | None = None, server: bool = False) -> None:
        """``pki/<name>.crt`` and ``.key`` signed by the cluster CA: a client certificate (CN is the user, O the
        group), or the API server's serving certificate."""
        ca, ca_key = pki.load_ca(self.path("pki", "ca.crt"), self.path("pki", "ca.key"))
        alt_names = ("localhost", "kubernetes", "kubernetes.default", "kubernetes.default.svc", "127.0.0.1", "10.96.0.1")
        cert, key = pki.issue(
            ca, ca_key, cn, usage=pki.SERVER if server else pki.CLIENT, days=365, organization=org,
            alt_names=alt_names if server else (),
        )  # fmt: skip
        pki.write_pem(self.path("pki", f"{name}.key"), key)
        pki.write_pem(self.path("pki", f"{name}.crt"), cert)

    def ensure_certificate(self, name: str, cn: str, org: str | None = None, server: str | None = None) -> str:
        """A client certificate, made once, and a kubeconfig for it (``<name>.kubeconfig``, reaching the API
        server at ``server`` when given); returns the kubeconfig's path."""
        if not os.path.exists(self.path("pki", f"{name}.crt")):
            self.issue_certificate(name, cn, org)
        self._write_kubeconfig(self.path(f"{name}.kubeconfig"), name, server)
        return self.path(f"{name}.kubeconfig")

    def ensure_pki(self) -> bool:
        """CA, serving and client certificates, service-account keys and kubeconfigs; True if created."""
        from cryptography.hazmat.primitives.asymmetric import rsa

        pki_dir = self.path("pki")
        if os.path.exists(os.path.join(pki_dir, "done")):
            return False
        os.makedirs(pki_dir, mode=0o700, exist_ok=True)
        ca, ca_key = pki.new_ca("kuberos-local-ca", days=3650)
        pki.write_pem(os.path.join(pki_dir, "ca.key"), ca_key)
        pki.write_pem(os.path.join(pki_dir, "ca.crt"), ca)

        self.issue_certificate("apiserver", "kube-apiserver", server=True)
        self.issue_certificate("admin", "kuberos-admin", "system:masters")
        self.issue_certificate("controller-manager", "system:kube-controller-manager")
        self.issue_certificate("scheduler", "system:kube-scheduler")
        self.issue_certificate("kwok", "kwok-controller", "system:masters")
        # The API server's client certificate towards kubelets (logs, exec, port-forward on real nodes).
        self.issue_certificate("apiserver-kubelet-client", "kube-apiserver-kubelet-client", "system:masters")
        sa_key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
        pki.write_pem(os.path.join(pki_dir, "sa.key"), sa_key)
        pki.write_pem(os.path.join(pki_dir, "sa.pub"), sa_key.public_key())
        for user in ("admin", "controller-manager", "scheduler", "kwok"):
            target = self.kubeconfig if user == "admin" else self.path(f"{user}.kubeconfig")
            self._write_kubeconfig(target, user)
        with open(os.path.join(pki_dir, "done"), "w", encoding="utf-8") as handle:
            handle.write("ok\n")
        self.log.append("generated certificates and kubeconfigs")
        return True

    def _write_kubeconfig(self, target: str, user: str, server: str | None = None) -> None:
        """A kubeconfig for ``pki/<user>.crt``; ``server``: another address of the API server (a relay), whose
        certificate is then checked for the name ``kubernetes``."""
        pki = self.path("pki")
        cluster = {"server": server or self.server, "certificate-authority": f"{pki}/ca.crt"}
        if server:
            cluster["tls-server-name"] = "kubernetes"
        config = {
            "apiVersion": "v1",
            "kind": "Config",
            "clusters": [{"name": "kuberos-local", "cluster": cluster}],
            "users": [{"name": user, "user": {"client-certificate": f"{pki}/{user}.crt", "client-key": f"{pki}/{user}.key"}}],
            "contexts": [{"name": "kuberos-local", "context": {"cluster": "kuberos-local", "user": user}}],
            "current-context": "kuberos-local",
        }
        with open(target, "w", encoding="utf-8") as handle:
            os.fchmod(handle.fileno(), 0o600)
            json.dump(config, handle, indent=2)  # JSON is valid YAML; every client reads it

    # -- processes ---------------------------------------------------------------------------------
    def command(self, component: str) -> list[str]:
        pki = self.path("pki")
        p = self.ports
        binary = self.binaries[component]
        if component == "etcd":
            return [
                binary, "--name=kuberos", f"--data-dir={self.path('etcd')}",
                f"--listen-client-urls=http://127.0.0.1:{p.etcd_client}", f"--advertise-client-urls=http://127.0.0.1:{p.etcd_client}",
                f"--listen-peer-urls=http://127.0.0.1:{p.etcd_peer}", f"--initial-advertise-peer-urls=http://127.0.0.1:{p.etcd_peer}",
                f"--initial-cluster=kuberos=http://127.0.0.1:{p.etcd_peer}", "--unsafe-no-fsync=true",
                "--quota-backend-bytes=4294967296", "--log-level=warn",
            ]  # fmt: skip
        if component == "kube-apiserver":
            return [
                binary, f"--etcd-servers=http://127.0.0.1:{p.etcd_client}", "--bind-address=127.0.0.1",
                f"--advertise-address={self.advertise_address}", f"--secure-port={p.apiserver}",
                f"--tls-cert-file={pki}/apiserver.crt", f"--tls-private-key-file={pki}/apiserver.key",
                f"--client-ca-file={pki}/ca.crt", f"--service-account-key-file={pki}/sa.pub",
                f"--service-account-signing-key-file={pki}/sa.key",
                "--service-account-issuer=https://kubernetes.default.svc.cluster.local",
                f"--service-cluster-ip-range={SERVICE_CIDR}", "--authorization-mode=Node,RBAC", "--anonymous-auth=false",
                "--allow-privileged=true", "--enable-priority-and-fairness=false", "--max-requests-inflight=2000",
                "--max-mutating-requests-inflight=1000",
                f"--kubelet-client-certificate={pki}/apiserver-kubelet-client.crt",
                f"--kubelet-client-key={pki}/apiserver-kubelet-client.key",
                "--kubelet-preferred-address-types=InternalIP",
                f"--default-unreachable-toleration-seconds={self.unreachable_toleration_s}",
                f"--default-not-ready-toleration-seconds={self.unreachable_toleration_s}",
            ]  # fmt: skip
        if component == "kube-controller-manager":
            return [
                *self._controller_flags(binary, "controller-manager", p.controller_manager),
                f"--service-account-private-key-file={pki}/sa.key", f"--root-ca-file={pki}/ca.crt",
                f"--cluster-signing-cert-file={pki}/ca.crt", f"--cluster-signing-key-file={pki}/ca.key",
                "--use-service-account-credentials=true", f"--service-cluster-ip-range={SERVICE_CIDR}",
                "--concurrent-deployment-syncs=20", "--concurrent-replicaset-syncs=20", "--node-monitor-grace-period=40s",
            ]  # fmt: skip
        if component == "kube-scheduler":
            return self._controller_flags(binary, "scheduler", p.scheduler)
        if component == "kwok":
            command = [
                binary, f"--kubeconfig={self.path('kwok.kubeconfig')}", "--manage-all-nodes=false",
                "--manage-nodes-with-annotation-selector=kwok.x-k8s.io/node=fake",
                f"--server-address=127.0.0.1:{p.kwok}", "--node-lease-duration-seconds=40",
            ]  # fmt: skip
            for stage in self.kwok_stages:
                command.append(f"--config={stage}")
            return command
        raise ValueError(component)

    def _controller_flags(self, binary: str, user: str, port: int) -> list[str]:
        """What kube-controller-manager and kube-scheduler share: their kubeconfig for the API, for
        delegated authentication and authorization, serving on loopback, no leader election."""
        kubeconfig = self.path(f"{user}.kubeconfig")
        return [
            binary, f"--kubeconfig={kubeconfig}", f"--authentication-kubeconfig={kubeconfig}",
            f"--authorization-kubeconfig={kubeconfig}", "--bind-address=127.0.0.1", f"--secure-port={port}",
            "--leader-elect=false", "--kube-api-qps=500", "--kube-api-burst=1000",
        ]  # fmt: skip

    def pid_of(self, component: str) -> int | None:
        """The pid of a running component started by us (checked against /proc), or None."""
        try:
            with open(self.path("run", f"{component}.pid"), encoding="utf-8") as handle:
                pid = int(handle.read().strip())
            with open(f"/proc/{pid}/cmdline", "rb") as handle:
                argv0 = handle.read().split(b"\0")[0].decode()
        except (OSError, ValueError):
            return None
        return pid if os.path.realpath(argv0) == os.path.realpath(self.binaries[component]) else None

    def start_component(self, component: str) -> None:
        os.makedirs(self.path("run"), exist_ok=True)
        os.makedirs(self.path("logs"), exist_ok=True)
        log = open(self.path("logs", f"{component}.log"), "ab")
        process = subprocess.Popen(
            self.command(component), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True, close_fds=True,
        )  # fmt: skip
        log.close()
        with open(self.path("run", f"{component}.pid"), "w", encoding="utf-8") as handle:
            handle.write(f"{process.pid}\n")
        self._children[component] = process
        self.log.append(f"started {component} (pid {process.pid})")

    def stop_component(self, component: str, timeout: float = 15.0) -> bool:
        pid = self.pid_of(component)
        if pid is None:
            return False
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and self.pid_of(component) == pid and alive(pid):
            time.sleep(0.1)
        if alive(pid):
            os.kill(pid, signal.SIGKILL)
        try:
            os.remove(self.path("run", f"{component}.pid"))
        except FileNotFoundError:
            pass
        self.log.append(f"stopped {component} (pid {pid})")
        return True

    # -- health ------------------------------------------------------------------------------------
    def get(self, path: str, timeout: float = 5.0) -> tuple[int, bytes]:
        tls = {
            "ca_path": self.path("pki", "ca.crt"),
            "client_cert": self.path("pki", "admin.crt"),
            "client_key": self.path("pki", "admin.key"),
        }
        try:
            with open_url(self.server + path, timeout=timeout, **tls) as response:
                return response.status, response.read()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read()
        except (urllib.error.URLError, OSError):
            return 0, b""

    def etcd_healthy(self) -> bool:
        try:
            with open_url(f"http://127.0.0.1:{self.ports.etcd_client}/health", timeout=3) as response:
                return b'"health":"true"' in response.read()
        except (urllib.error.URLError, OSError):
            return False

    def apiserver_ready(self) -> bool:
        status, _body = self.get("/readyz")
        return status == 200

    def _wait(self, what: str, check, timeout: float, component: str) -> None:
        deadline = time.monotonic() + timeout
        retried = False
        while time.monotonic() < deadline:
            if check():
                return
            child = self._children.get(component)
            code = child.poll() if child is not None else None
            # A child of ours is judged by its exit status: right after the fork, before the exec, its command
            # line is still Python's, and pid_of() would take it for another program.
            gone = code is not None if child is not None else self.pid_of(component) is None
            if gone:
                if not retried and child is not None:
                    # One more try: a program that dies at once (seen rarely under heavy load) usually starts.
                    self.log.append(f"{component} exited at once (status {code}); starting it again")
                    retried = True
                    time.sleep(1)
                    self.start_component(component)
                    continue
                log = self.path("logs", component + ".log")
                raise RuntimeError(f"{component} exited (status {code}); see {log}:\n{self.tail(component)}")
            time.sleep(0.2)
        log = self.path("logs", component + ".log")
        raise RuntimeError(f"{what} not ready after {timeout:.0f} s; see {log}:\n{self.tail(component)}")

    def tail(self, component: str, lines: int = 15) -> str:
        try:
            with open(self.path("logs", f"{component}.log"), "rb") as handle:
                return b"\n".join(handle.read().splitlines()[-lines:]).decode(errors="replace")
        except OSError:
            return "(no log)"

    def running(self) -> dict[str, int | None]:
        return {c: self.pid_of(c) for c in COMPONENTS}

    # -- lifecycle -----------------------------------------------------------------------------------
    def start(self, timeout: float = 90.0) -> bool:
        """Start whatever is not running; True when anything was started."""
        missing = [c for c in COMPONENTS if not os.access(self.binaries.get(c, ""), os.X_OK)]
        if missing:
            raise RuntimeError(f"binaries not built: {', '.join(missing)} (run the build first)")
        os.makedirs(self.state_dir, mode=0o700, exist_ok=True)
        changed = self.ensure_pki()
        if not os.path.exists(self.path("pki", "apiserver-kubelet-client.crt")):  # a cluster made before real nodes
            self.issue_certificate("apiserver-kubelet-client", "kube-apiserver-kubelet-client", "system:masters")
        started = []
        try:
            for component in COMPONENTS:
                if self.pid_of(component) is None:
                    self.start_component(component)
                    started.append(component)
                    changed = True
                if component == "etcd":
                    self._wait("etcd", self.etcd_healthy, timeout, "etcd")
                elif component == "kube-apiserver":
                    self._wait("kube-apiserver", self.apiserver_ready, timeout, "kube-apiserver")
        except RuntimeError:
            for component in reversed(started):  # leave nothing half-started behind
                self.stop_component(component)
            raise
        return changed

    def stop(self) -> bool:
        changed = False
        for component in reversed(COMPONENTS):
            changed = self.stop_component(component) or changed
        return changed
