"""The stacked etcd of a kubeadm site: its members as kubeadm named them, snapshot names and their retention, what
etcdutl says of a snapshot, and each control plane's part of a restore.

Pure: inventory facts, the etcd static pod's manifest (as a dict) and etcdutl's output in, plain data out; every
problem reported at once (``SpecError``), naming the host and the field.

- kubeadm names a control plane's etcd member after its node (``--name=<node name>``) and advertises it on
  ``https://<advertise address>:2380``, the address the API server advertises (``kuberos_address``, else
  ``ansible_host``); ``initial_cluster`` joins every member as ``name=peer URL``, the form of ``--initial-cluster``.
- A snapshot is named ``etcd-snapshot-<UTC time>-<node>.db`` (``20261207T031500Z``): the names sort by time, and
  ``snapshots_to_remove`` keeps the newest ``keep`` of the names of that form (other files are never touched).
- A restore rebuilds every member's data directory from one snapshot, offline, with a new cluster token (the old
  members can never rejoin the new cluster by mistake) and the revision bumped and marked compacted, so that every
  watcher of the API server (controllers, kubelets, informers) lists afresh instead of resuming at a revision the
  snapshot never reached (etcd's and Kubernetes' advice for restoring a cluster Kubernetes uses).
"""

from __future__ import annotations

import ipaddress
import json
import re
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError

SOURCE = "etcd"
PEER_PORT = 2380
SNAPSHOT_NAME = re.compile(r"^etcd-snapshot-(?P<stamp>\d{8}T\d{6}Z)-(?P<node>[A-Za-z0-9][A-Za-z0-9._-]*)\.db\Z")
STAMP = re.compile(r"^\d{8}T\d{6}Z\Z")
# A node name as Kubernetes accepts it (a DNS subdomain), which is also safe in a file name and a container id.
NODE_NAME = re.compile(r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*\Z")
# etcdutl's default; Kubernetes' documentation uses a billion: far beyond what a site writes between a snapshot and
# its restore.
DEFAULT_BUMP_REVISION = 1_000_000_000
ETCD_CONTAINER = "etcd"
DATA_VOLUME = "etcd-data"  # kubeadm's name of the volume of etcd's data directory


@dataclass(frozen=True)
class Member:
    """One control plane's etcd member, as kubeadm made it."""

    host: str  # inventory name
    name: str  # the node name: etcd's --name
    address: str  # the API server's advertise address, also etcd's

    @property
    def peer_url(self) -> str:
        return peer_url(self.address)


def peer_url(address: str) -> str:
    """``https://<address>:2380``, an IPv6 address in brackets (Go's net.JoinHostPort, as kubeadm writes it)."""
    host = str(address)
    try:
        if ipaddress.ip_address(host).version == 6:
            host = f"[{host}]"
    except ValueError:
        pass
    return f"https://{host}:{PEER_PORT}"


def members(control_planes, node_names: dict, addresses: dict) -> list[Member]:
    """The etcd members of the control planes, in the inventory's order. ``node_names`` and ``addresses`` map each
    inventory host to its node name (``kuberos_node_name``, else the host) and its address (``kuberos_address``,
    else ``ansible_host``). Unknown, duplicate or unusable names and addresses are reported together."""
    problems: list[Problem] = []
    hosts = [str(h) for h in control_planes or []]
    if not hosts:
        problems.append(Problem(SOURCE, "groups.control_plane", "is empty: the site's etcd members are its control planes"))
    found: list[Member] = []
    for index, host in enumerate(hosts):
        name, address = str(node_names.get(host) or ""), str(addresses.get(host) or "")
        if not NODE_NAME.match(name):
            problems.append(Problem(SOURCE, f"hosts.{host}.kuberos_node_name", f"{name!r} is not a node name kubeadm gives etcd"))
        if not address or any(c in address for c in "/ ,=@"):
            problems.append(Problem(SOURCE, f"hosts.{host}.kuberos_address", f"{address!r} is not an address etcd advertises"))
        if hosts.index(host) != index:
            problems.append(Problem(SOURCE, f"groups.control_plane[{index}]", f"{host} is listed twice"))
            continue
        found.append(Member(host, name, address))
    for what, key in (("node name", lambda m: m.name), ("peer URL", lambda m: m.peer_url)):
        seen: dict[str, str] = {}
        for member in found:
            if key(member) in seen:
                problems.append(
                    Problem(
                        SOURCE,
                        f"hosts.{member.host}",
                        f"has the {what} {key(member)} of {seen[key(member)]}: etcd members need their own",
                    )
                )
            seen.setdefault(key(member), member.host)
    if problems:
        raise SpecError(problems, "invalid etcd members")
    return found


def initial_cluster(found: list[Member]) -> str:
    """``--initial-cluster``: ``name=peer URL`` of every member, comma-separated, in the inventory's order."""
    return ",".join(f"{m.name}={m.peer_url}" for m in found)


# ------------------------------------------------------------------------------------------------ snapshots


def snapshot_name(stamp: str, node: str) -> str:
    """The file name of a snapshot taken at ``stamp`` (UTC, ``20261207T031500Z``) from ``node``'s member."""
    problems = []
    if not STAMP.match(str(stamp)):
        problems.append(Problem(SOURCE, "stamp", f"{stamp!r} is not a UTC time like 20261207T031500Z"))
    if not NODE_NAME.match(str(node)):
        problems.append(Problem(SOURCE, "node", f"{node!r} is not a node name"))
    if problems:
        raise SpecError(problems, "invalid snapshot name")
    return f"etcd-snapshot-{stamp}-{node}.db"


def snapshots_to_remove(paths, keep) -> list[str]:
    """The snapshots to remove so that the newest ``keep`` stay: of ``paths`` (file paths or names), those whose
    name has the form of ``snapshot_name``, oldest first. Any other file is left alone, whatever its name."""
    if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
        raise SpecError(
            [Problem(SOURCE, "keep", f"{keep!r} is not a number of snapshots to keep (1 or more)")], "invalid retention"
        )
    dated = []
    for path in paths or []:
        match = SNAPSHOT_NAME.match(str(path).rsplit("/", 1)[-1])
        if match:
            dated.append((match["stamp"], str(path)))
    dated.sort()
    return [path for _stamp, path in dated[: max(0, len(dated) - keep)]]


def _ready(pod: dict) -> bool:
    conditions = (pod.get("status") or {}).get("conditions") or []
    return any(c.get("type") == "Ready" and c.get("status") == "True" for c in conditions if isinstance(c, dict))


def backup_source(pods, node_hosts: dict, stamp: str, preferred: str = "") -> dict:
    """Where to take a snapshot: the first of the etcd static pods (``pods``, as the API lists them) that runs, is
    Ready and runs on a control plane of the inventory (``node_hosts``: node name -> inventory host), or the one on
    ``preferred`` (an inventory host), which must be so. Returns the pod, its node and host, and the snapshot's
    name; when no pod will do, every pod and why not."""
    problems: list[Problem] = []
    usable = []
    for pod in pods or []:
        meta, spec = pod.get("metadata") or {}, pod.get("spec") or {}
        name, node = str(meta.get("name") or ""), str(spec.get("nodeName") or "")
        phase = (pod.get("status") or {}).get("phase")
        if node not in node_hosts:
            why = f"its node {node!r} is not a control plane of the inventory"
        elif phase != "Running":
            why = f"it is {phase or 'not scheduled'}, not Running"
        elif not _ready(pod):
            why = "it is not Ready (etcd's own health check fails)"
        else:
            usable.append({"pod": name, "node": node, "host": node_hosts[node]})
            continue
        problems.append(Problem(SOURCE, f"pod kube-system/{name}", why))
    if preferred:
        chosen = [u for u in usable if u["host"] == preferred]
        if not chosen:
            problems.append(Problem(SOURCE, "preferred control plane", f"{preferred} runs no Running and Ready etcd pod"))
    else:
        chosen = usable
    if not chosen:
        if not pods:
            problems.append(
                Problem(
                    SOURCE,
                    "kube-system",
                    "no etcd static pod (label component=etcd): is this a kubeadm cluster with stacked etcd?",
                )
            )
        raise SpecError(problems, "no healthy etcd member to take a snapshot from")
    return {**chosen[0], "name": snapshot_name(stamp, chosen[0]["node"])}


def human_size(size: int) -> str:
    """``12.3 MiB``: a size in bytes for a person."""
    value = float(size)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{int(value)} B" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} GiB"  # pragma: no cover


def snapshot_status(text: str) -> dict:
    """What ``etcdutl snapshot status -w json`` (or ``etcdctl``'s) said of a snapshot: its revision, key count, size
    and hash. A snapshot with no revision or no keys is refused: it holds no cluster."""
    body = str(text or "").strip()
    start = body.find("{")
    try:
        status = json.loads(body[start:]) if start >= 0 else None
    except ValueError:
        status = None
    fields = ("hash", "revision", "totalKey", "totalSize")
    if not isinstance(status, dict) or not all(
        isinstance(status.get(f), int) and not isinstance(status.get(f), bool) for f in fields
    ):
        shown = body[:200] or "nothing"
        raise SpecError(
            [Problem(SOURCE, "snapshot status", f"not etcdutl's JSON status of a snapshot: {shown!r}")],
            "unreadable snapshot status",
        )
    if status["revision"] < 1 or status["totalKey"] < 1:
        raise SpecError(
            [
                Problem(
                    SOURCE,
                    "snapshot status",
                    f"revision {status['revision']}, {status['totalKey']} keys: the snapshot holds no cluster",
                )
            ],
            "empty snapshot",
        )
    return {
        "hash": status["hash"],
        "revision": status["revision"],
        "keys": status["totalKey"],
        "size_bytes": status["totalSize"],
        "size": human_size(status["totalSize"]),
        "version": str(status.get("version", "")),
    }


# ------------------------------------------------------------------------------------------------ restore


@dataclass(frozen=True)
class EtcdManifest:
    """What a restore needs from a control plane's etcd static pod manifest."""

    image: str
    name: str
    data_dir: str
    peer_url: str


def _flags(command) -> dict[str, str]:
    """``--name=value`` arguments of a container's command as {name: value}."""
    found = {}
    for argument in command or []:
        text = str(argument)
        if text.startswith("--") and "=" in text:
            key, _sep, value = text[2:].partition("=")
            found[key] = value
    return found


def etcd_manifest(manifest, host: str) -> EtcdManifest:
    """The image, member name, data directory and peer URL of ``host``'s etcd static pod (kubeadm's ``etcd.yaml``,
    parsed); the data directory must be the host path of the data volume (as kubeadm writes it), since the restore
    writes there from outside the pod."""
    where = f"{host}: etcd.yaml"
    problems: list[Problem] = []
    spec = (manifest or {}).get("spec") if isinstance(manifest, dict) else None
    containers = [c for c in (spec or {}).get("containers") or [] if isinstance(c, dict) and c.get("name") == ETCD_CONTAINER]
    if not containers:
        raise SpecError(
            [Problem(SOURCE, where, "has no container named etcd: is it kubeadm's etcd static pod?")], "unusable etcd manifest"
        )
    container = containers[0]
    flags = _flags(container.get("command"))
    for key in ("name", "data-dir", "initial-advertise-peer-urls"):
        if not flags.get(key):
            problems.append(Problem(SOURCE, f"{where}: spec.containers[etcd].command", f"has no --{key}"))
    image = str(container.get("image") or "")
    if not image:
        problems.append(Problem(SOURCE, f"{where}: spec.containers[etcd].image", "is empty"))
    data_dir = flags.get("data-dir", "")
    if data_dir and (not data_dir.startswith("/") or data_dir.rstrip("/").count("/") < 2):
        problems.append(
            Problem(SOURCE, f"{where}: --data-dir", f"{data_dir!r}: expected an absolute path two levels deep or more")
        )
    volumes = {v.get("name"): v for v in (spec or {}).get("volumes") or [] if isinstance(v, dict)}
    host_path = ((volumes.get(DATA_VOLUME) or {}).get("hostPath") or {}).get("path", "")
    if data_dir and host_path.rstrip("/") != data_dir.rstrip("/"):
        problems.append(
            Problem(SOURCE, f"{where}: volumes[{DATA_VOLUME}].hostPath", f"{host_path!r} is not the data directory {data_dir!r}")
        )
    if problems:
        raise SpecError(problems, "unusable etcd manifest")
    return EtcdManifest(image, flags["name"], data_dir.rstrip("/"), flags["initial-advertise-peer-urls"])


def _ctr_run(parent: str, image: str, container: str) -> list[str]:
    """``ctr run`` of a one-off container of ``image`` in the CRI's namespace, ``parent`` (the folder of etcd's data
    directory, where the snapshot lies too) bound in at the same path, removed when it ends."""
    return [
        "ctr",
        "--namespace",
        "k8s.io",
        "run",
        "--rm",
        "--mount",
        f"type=bind,src={parent},dst={parent},options=rbind:rw",
        image,
        container,
    ]


def restore_plan(found: list[Member], host: str, manifest, stamp: str, bump_revision: int = DEFAULT_BUMP_REVISION) -> dict:
    """``host``'s part of restoring every member from one snapshot at ``stamp`` (UTC, as in the snapshot names):
    where the snapshot is copied, where etcdutl writes the new data directory, where the old one is kept, and the
    ``ctr run`` that runs etcdutl from the etcd image the host already has (and the one that reads the snapshot's
    status first). The member's name and peer URL in the inventory must be those in its running manifest: a restore
    with others would make a cluster the manifests do not describe."""
    member = next((m for m in found if m.host == host), None)
    if member is None:
        raise SpecError([Problem(SOURCE, f"hosts.{host}", "is not one of the control planes")], "invalid restore")
    if not STAMP.match(str(stamp)):
        raise SpecError([Problem(SOURCE, "stamp", f"{stamp!r} is not a UTC time like 20261207T031500Z")], "invalid restore")
    if isinstance(bump_revision, bool) or not isinstance(bump_revision, int) or bump_revision < 1:
        raise SpecError([Problem(SOURCE, "bump_revision", f"{bump_revision!r}: expected a positive number")], "invalid restore")
    pod = etcd_manifest(manifest, host)
    problems = []
    if pod.name != member.name:
        problems.append(
            Problem(SOURCE, f"hosts.{host}", f"its etcd member is named {pod.name!r}, the inventory says {member.name!r}")
        )
    if pod.peer_url != member.peer_url:
        problems.append(
            Problem(SOURCE, f"hosts.{host}", f"its etcd member advertises {pod.peer_url}, the inventory says {member.peer_url}")
        )
    if problems:
        raise SpecError(problems, "the inventory does not describe the running etcd members")
    parent = pod.data_dir.rsplit("/", 1)[0]
    snapshot = f"{parent}/etcd-restore-{stamp}.db"
    restored = f"{pod.data_dir}.restored-{stamp}"
    token = f"kuberos-restore-{stamp.lower()}"
    restore = [
        "etcdutl", "snapshot", "restore", snapshot,
        "--name", member.name,
        "--initial-cluster", initial_cluster(found),
        "--initial-cluster-token", token,
        "--initial-advertise-peer-urls", member.peer_url,
        "--data-dir", restored,
        "--bump-revision", str(bump_revision), "--mark-compacted",
    ]  # fmt: skip
    run = [*_ctr_run(parent, pod.image, f"kuberos-etcd-restore-{stamp.lower()}"), *restore]
    status = [
        *_ctr_run(parent, pod.image, f"kuberos-etcd-status-{stamp.lower()}"),
        "etcdutl",
        "snapshot",
        "status",
        snapshot,
        "-w",
        "json",
    ]
    return {
        "host": host,
        "name": member.name,
        "peer_url": member.peer_url,
        "initial_cluster": initial_cluster(found),
        "token": token,
        "image": pod.image,
        "data_dir": pod.data_dir,
        "snapshot": snapshot,
        "restored_dir": restored,
        "kept_dir": f"{pod.data_dir}.before-restore-{stamp}",
        "restore_argv": run,
        "status_argv": status,
    }
