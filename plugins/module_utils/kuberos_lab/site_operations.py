"""Day 2 of the lab site: the control planes' certificates renewed and the site's etcd backed up and restored, as
steps of the site chain (``site_lab.SiteChain``, ``tests/site``), each recording its figures in ``chain.figures``.

- ``renew_certificates``: ``certificates.yml -e renew=true`` while a thread asks the API through the virtual IP every
  half second; the API server certificate's notAfter on every control plane, read from the machine's
  ``/etc/kubernetes/pki/apiserver.crt`` before and after, must move later.
- ``backup_and_restore``: ``etcd_backup.yml`` into the lab's state, a named ConfigMap deleted, ``etcd_restore.yml``
  refused without its confirmation and then run with it; the object must be back and every node that was Ready
  before Ready again.

Every wait and every request is bounded. Lab only: nothing in the collection imports it.
"""

from __future__ import annotations

import glob
import itertools
import os
import stat
import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import site_lab

APISERVER_CERTIFICATE = ("etc", "kubernetes", "pki", "apiserver.crt")
CERTIFICATE_MAX_BYTES = 64 * 1024
SAMPLE_INTERVAL_S = 0.4  # on a fixed schedule: samples stay within 0.5 s of each other on a busy machine too
SAMPLE_TIMEOUT_S = 1.0  # one request's read bound: a request that takes longer counts as the API not answering
SAMPLES_MAX = 14_400  # two hours of samples at most, whatever the playbook does


def apiserver_not_after(machines, name: str):
    """The notAfter (aware, UTC) of the API server certificate on lab machine ``name``, read from its root filesystem;
    None when there is none."""
    from cryptography import x509

    path = os.path.join(machines.rootfs(name), *APISERVER_CERTIFICATE)
    try:
        with open(path, "rb") as handle:
            data = handle.read(CERTIFICATE_MAX_BYTES + 1)
    except FileNotFoundError:
        return None
    if len(data) > CERTIFICATE_MAX_BYTES:
        raise site_lab.SiteLabError(f"{name}: {path} is larger than {CERTIFICATE_MAX_BYTES} bytes: not a certificate")
    return x509.load_pem_x509_certificate(data).not_valid_after_utc


def longest_outage(samples: list[tuple[float, bool]]) -> float:
    """The longest time the API did not answer, from ``samples`` ((monotonic time, answered), in order): from the
    first unanswered sample of a run to the next answered one (to the last sample when it never answered again)."""
    longest, down_since = 0.0, None
    for moment, answered in samples:
        if not answered and down_since is None:
            down_since = moment
        elif answered and down_since is not None:
            longest, down_since = max(longest, moment - down_since), None
    if down_since is not None and samples:
        longest = max(longest, samples[-1][0] - down_since)
    return longest


class ApiSampler:
    """Asks the API (through the chain's kubeconfig: the site's endpoint, the virtual IP) for a Namespace every
    ``interval`` seconds (0.4 by default, on a fixed schedule), each request in a worker of its own so that one that
    hangs does not delay the next, bounded by ``SAMPLE_TIMEOUT_S``; until stopped, at most ``limit`` samples or
    ``max_s`` seconds. ``samples``: (monotonic time the request started, answered), in order."""

    def __init__(self, kube: Kube, interval: float = SAMPLE_INTERVAL_S, limit: int = SAMPLES_MAX, max_s: float = 7200):
        from concurrent.futures import ThreadPoolExecutor

        self.kube = Kube(kube.clients, read_timeout=SAMPLE_TIMEOUT_S)
        self.interval, self.limit, self.max_s = min(interval, 0.5), limit, max_s
        self._pool = ThreadPoolExecutor(max_workers=int(SAMPLE_TIMEOUT_S / self.interval) + 2, thread_name_prefix="api-sample")
        self._asked: list = []  # (start time, future)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="api-sampler", daemon=True)

    def _answered(self) -> bool:
        try:
            return self.kube.get("Namespace", "kube-system") is not None
        except Exception:  # any failure (refused, reset, timed out, 5xx) is the API not answering
            return False

    def _run(self) -> None:
        started = time.monotonic()
        while not self._stop.is_set() and len(self._asked) < self.limit and time.monotonic() - started < self.max_s:
            self._asked.append((time.monotonic(), self._pool.submit(self._answered)))
            next_tick = started + len(self._asked) * self.interval
            self._stop.wait(max(0.0, next_tick - time.monotonic()))

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *_exc):
        self._stop.set()
        self._thread.join(self.interval * 4)
        self._pool.shutdown(wait=True, cancel_futures=True)  # the requests still running end within their bound

    @property
    def samples(self) -> list[tuple[float, bool]]:
        return [(asked, future.result()) for asked, future in self._asked if future.done() and not future.cancelled()]

    def longest_outage(self) -> float:
        return longest_outage(self.samples)

    def widest_gap(self) -> float:
        """The longest time between two samples' starts (the schedule's 0.4 s, more on a starved machine)."""
        times = [moment for moment, _answered in self.samples]
        return max((b - a for a, b in itertools.pairwise(times)), default=0.0)


def renew_certificates(chain, timeout: float = site_lab.PLAYBOOK_TIMEOUT):
    """certificates.yml with renewal, one control plane at a time, while the API is sampled through the virtual IP.
    Records ``cert_renew_s``, ``cert_not_after_moved`` (every control plane's API server certificate ends later than
    before), ``api_unavailable_during_renew_max_s``, ``api_samples_during_renew`` and ``api_sample_widest_gap_s``.
    Returns the playbook's result with ``not_after`` (machine -> (before, after)) and ``samples``."""
    machines = chain.lab.machines
    before = {name: apiserver_not_after(machines, name) for name in site_lab.CONTROL_PLANES}
    with ApiSampler(chain.kube) as sampler:
        result = chain._play("certificates.yml", "-e", "renew=true", timeout=timeout)
    after = {name: apiserver_not_after(machines, name) for name in site_lab.CONTROL_PLANES}
    chain.figures["cert_renew_s"] = round(result.seconds, 1)
    chain.figures["cert_not_after_moved"] = all(
        before[n] is not None and after[n] is not None and after[n] > before[n] for n in before
    )
    chain.figures["api_unavailable_during_renew_max_s"] = round(sampler.longest_outage(), 1)
    chain.figures["api_samples_during_renew"] = len(sampler.samples)
    chain.figures["api_sample_widest_gap_s"] = round(sampler.widest_gap(), 2)
    result.not_after = {name: (before[name], after[name]) for name in before}
    result.samples = sampler.samples
    if result.returncode == 0:
        chain.connect()  # the renewed admin.conf
    return result


# What the backup and the restore write on a control plane and must remove (relative to the machine's root).
LEFTOVER_PATTERNS = (
    "var/lib/etcd/etcd-snapshot-*",  # the snapshot in the pod's data directory
    "var/tmp/kuberos-etcd-backup-*",  # the SSH user's copy
    "var/lib/etcd-restore-*.db",  # the restore's copy of the snapshot
    "var/lib/etcd.restored-*",  # a restored data directory not moved into place
    "etc/kubernetes/etcd-restore-held-manifests",
    "etc/kubernetes/certificates-held-manifests",
)


def leftovers(machines) -> list[str]:
    """What the backup, the restore or the renewal left on the control planes (machine:path)."""
    found = []
    for name in site_lab.CONTROL_PLANES:
        root = machines.rootfs(name)
        for pattern in LEFTOVER_PATTERNS:
            found += [f"{name}:/{os.path.relpath(path, root)}" for path in glob.glob(os.path.join(root, pattern))]
    return sorted(found)


def _mode(path: str) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def _ready_nodes(kube: Kube) -> set[str]:
    return {name for name, node in site_lab.nodes(kube).items() if node["ready"]}


def backup_and_restore(chain, namespace: str, configmap_name: str, timeout: float = site_lab.PLAYBOOK_TIMEOUT) -> dict:
    """etcd_backup.yml into ``<lab state>/etcd-backups``, then the ConfigMap ``namespace/configmap_name`` (which must
    exist: the test passes a deployment record) deleted, etcd_restore.yml refused without the confirmation and run
    with it. Records ``etcd_backup_s``, ``etcd_restore_s``, ``etcd_restore_refused_unconfirmed``,
    ``restored_objects_back`` and ``nodes_ready_after_restore``. Returns what the test asserts on: both runs, the
    snapshot, its mode and its folder's, the refusal, the control planes that kept their old data directory, whether
    the object is back and the nodes Ready again."""
    kube = chain.kube
    if kube.get("ConfigMap", configmap_name, namespace) is None:
        raise site_lab.SiteLabError(f"ConfigMap {namespace}/{configmap_name} does not exist: nothing to restore")
    ready_before = _ready_nodes(kube)
    folder = chain.lab.path("etcd-backups")
    found: dict = {"backup": None, "restore": None, "snapshot": "", "snapshot_mode": None, "folder_mode": None,
                   "refused": None, "leftovers": [], "kept_old_data": [], "restored_objects_back": False,
                   "nodes_ready": False}  # fmt: skip

    backup = chain._play("etcd_backup.yml", "-e", f"etcd_backup_dir={folder}", timeout=timeout)
    chain.figures["etcd_backup_s"] = round(backup.seconds, 1)
    found["backup"] = backup
    snapshots = sorted(glob.glob(os.path.join(folder, "etcd-snapshot-*.db")))
    if backup.returncode != 0 or not snapshots:
        return found
    snapshot = snapshots[-1]
    found.update(snapshot=snapshot, snapshot_mode=_mode(snapshot), folder_mode=_mode(folder))

    kube.delete("ConfigMap", configmap_name, namespace)
    site_lab.wait_for(
        f"ConfigMap {namespace}/{configmap_name} deleted", lambda: kube.get("ConfigMap", configmap_name, namespace) is None, 60, 1
    )

    refused = chain._play("etcd_restore.yml", "-e", f"etcd_restore_snapshot={snapshot}", timeout=300)
    found["refused"] = refused
    chain.figures["etcd_restore_refused_unconfirmed"] = refused.returncode != 0 and "Refusing to restore" in refused.stdout

    name = os.path.basename(snapshot)
    restore = chain._play("etcd_restore.yml", "-e", f"etcd_restore_snapshot={snapshot}", "-e", f"etcd_restore_confirm={name}",
                          timeout=timeout)  # fmt: skip
    chain.figures["etcd_restore_s"] = round(restore.seconds, 1)
    found["restore"] = restore
    found["leftovers"] = leftovers(chain.lab.machines)
    found["kept_old_data"] = sorted(
        machine for machine in site_lab.CONTROL_PLANES
        if glob.glob(os.path.join(chain.lab.machines.rootfs(machine), "var", "lib", "etcd.before-restore-*"))
    )  # fmt: skip
    if restore.returncode == 0:
        chain.connect()

        def back():
            return chain.kube.get("ConfigMap", configmap_name, namespace) is not None

        try:
            found["restored_objects_back"] = bool(site_lab.wait_for(f"ConfigMap {namespace}/{configmap_name} back", back, 120))
            found["nodes_ready"] = bool(site_lab.wait_for("the nodes Ready before the restore Ready again",
                                                          lambda: ready_before <= _ready_nodes(chain.kube), 300))  # fmt: skip
        except site_lab.SiteLabError as error:
            found["error"] = str(error)
    chain.figures["restored_objects_back"] = found["restored_objects_back"]
    chain.figures["nodes_ready_after_restore"] = found["nodes_ready"]
    return found
