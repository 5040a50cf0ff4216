"""kubeadm configuration (v1beta4) for every machine of the inventory: the first control plane's
InitConfiguration and ClusterConfiguration, the JoinConfiguration of additional control planes and
of workers, and the KubeletConfiguration.

Pure: plain data in, plain data (and YAML text) out. The node labels and taints are the ones of
``labels.py``; labels a kubelet may not set on its own Node (NodeRestriction) are left out of
``--node-labels`` and returned separately, for the ``node_labels`` role to apply through the API.

Join secrets (the bootstrap token, the CA certificate hash, the certificate key of the control-plane
certificates) are only ever put into the documents when they are given; otherwise obvious placeholders
stand in, so that the same documents can be shown, diffed and validated in check mode.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError, describe
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import Inventory, Node
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.third_party import yaml

API_VERSION = "kubeadm.k8s.io/v1beta4"
KUBELET_API_VERSION = "kubelet.config.k8s.io/v1beta1"
KUBE_PROXY_API_VERSION = "kubeproxy.config.k8s.io/v1alpha1"
DEFAULT_KUBERNETES_VERSION = "v1.34.4"
DEFAULT_POD_CIDR = "10.244.0.0/16"
DEFAULT_SERVICE_CIDR = "10.96.0.0/12"
DEFAULT_API_PORT = 6443
DEFAULT_CRI_SOCKET = "unix:///run/containerd/containerd.sock"

# Stand-ins for the join secrets when they are not known (check mode, previews): valid in form, so that
# `kubeadm config validate` checks everything else, and recognisable at a glance.
PLACEHOLDER_TOKEN = "abcdef.0123456789abcdef"
PLACEHOLDER_CA_CERT_HASH = "sha256:" + "0" * 64
PLACEHOLDER_CERTIFICATE_KEY = "0" * 64

INIT = "init"
JOIN_CONTROL_PLANE = "join-control-plane"
JOIN_WORKER = "join-worker"

SOURCE = "inventory"
_VERSION = re.compile(r"^v(0|[1-9]\d*)\.(0|[1-9]\d*)\.(0|[1-9]\d*)(-[0-9A-Za-z.-]+)?(\+[0-9A-Za-z.-]+)?\Z")
_DNS_LABEL = r"[a-z0-9]([-a-z0-9]{0,61}[a-z0-9])?"
_DNS_NAME = re.compile(rf"^{_DNS_LABEL}(\.{_DNS_LABEL})*\Z")
# A registry path kubeadm prefixes to its images: host[:port] then path segments, e.g. mirror.site.example:5000/k8s.
_IMAGE_REPOSITORY = re.compile(r"^[a-z0-9]([-a-z0-9.]*[a-z0-9])?(:[0-9]{1,5})?(/[a-z0-9]+([._-][a-z0-9]+)*)*\Z")
_IMAGE_TAG = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}\Z")
CGROUP_DRIVERS = ("systemd", "cgroupfs")
# The kubelet's eviction signals (evictionHard keys) and a threshold: a quantity such as 500Mi, or a share such as 5%.
EVICTION_SIGNALS = (
    "memory.available", "nodefs.available", "nodefs.inodesFree", "imagefs.available", "imagefs.inodesFree",
    "containerfs.available", "containerfs.inodesFree", "pid.available",
)  # fmt: skip
_EVICTION_THRESHOLD = re.compile(r"^(\d+(\.\d+)?%|\d+(\.\d+)?([KMGTPE]i?|[kmMGTPE])?)\Z")
INIT_TOKEN_TTL = "15m0s"
INIT_TOKEN_DESCRIPTION = "made by kubeadm init; KubeROS joins with their own"
_TOKEN = re.compile(r"--token[= ]+([a-z0-9]{6}\.[a-z0-9]{16})(?=\s|$)")
_CA_HASH = re.compile(r"--discovery-token-ca-cert-hash[= ]+(sha256:[a-f0-9]{64})(?=\s|$)")
_CERT_KEY = re.compile(r"^\s*([a-f0-9]{64})\s*$", re.M)
_LABEL_NAME = re.compile(r"^[A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?\Z")
_LABEL_VALUE = re.compile(r"^([A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?)?\Z")
# Kubernetes refuses (kubelet --node-labels and the NodeRestriction admission plugin) labels a kubelet sets on its
# own Node under these namespaces, except the few below (k8s.io/kubelet/pkg/apis/well_known_labels.go).
_RESTRICTED_NAMESPACES = ("kubernetes.io", "k8s.io")
_KUBELET_LABELS = frozenset(
    {
        "kubernetes.io/hostname", "kubernetes.io/os", "kubernetes.io/arch", "beta.kubernetes.io/os",
        "beta.kubernetes.io/arch", "beta.kubernetes.io/instance-type", "node.kubernetes.io/instance-type",
        "topology.kubernetes.io/zone", "topology.kubernetes.io/region", "failure-domain.beta.kubernetes.io/zone",
        "failure-domain.beta.kubernetes.io/region",
    }
)  # fmt: skip
_KUBELET_LABEL_NAMESPACES = ("kubelet.kubernetes.io", "node.kubernetes.io")


@dataclass(frozen=True)
class Machine:
    """An inventory host as kubeadm sees it: its node, and its addresses on the site network and in the VPN."""

    host: str
    node: Node
    address: str
    vpn_address: str | None = None


@dataclass(frozen=True)
class ClusterSettings:
    """Site-wide settings, validated; ``control_plane_endpoint`` is always ``host:port``."""

    kubernetes_version: str
    pod_cidr: str
    service_cidr: str
    control_plane_endpoint: str
    cert_sans: tuple[str, ...]
    cluster_name: str = "kubernetes"
    cri_socket: str = DEFAULT_CRI_SOCKET
    bind_port: int = DEFAULT_API_PORT
    control_plane_schedulable: bool = True
    cgroup_driver: str = "systemd"
    image_repository: str = ""
    etcd_image_tag: str = ""
    coredns_image_tag: str = ""
    conntrack_max_per_core: int | None = None
    eviction_hard: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class JoinSecrets:
    """What a node needs to join; the defaults are placeholders (``placeholders`` is then true)."""

    token: str = PLACEHOLDER_TOKEN
    ca_cert_hashes: tuple[str, ...] = (PLACEHOLDER_CA_CERT_HASH,)
    certificate_key: str = PLACEHOLDER_CERTIFICATE_KEY
    placeholders: bool = field(default=True)


# ---------------------------------------------------------------------------------------------- validation


def _problem(path: str, value, reason: str) -> Problem:
    return Problem(SOURCE, path, f"{describe(value)} is not valid; {reason}")


def is_ip(value) -> bool:
    try:
        ipaddress.ip_address(str(value))
    except ValueError:
        return False
    return True


def _is_host(value: str) -> bool:
    return is_ip(value) or (len(value) <= 253 and bool(_DNS_NAME.match(value)))


def split_endpoint(value) -> tuple[str, int]:
    """``host:port`` (``[v6]:port`` for IPv6) into its parts; ValueError with the reason."""
    if not isinstance(value, str) or not value:
        raise ValueError("expected host:port, e.g. 10.0.0.10:6443 or k8s.site.example:6443")
    match = re.match(r"^\[([0-9A-Fa-f:.]+)\]:(\d+)\Z", value) or re.match(r"^([^:\[\]]+):(\d+)\Z", value)
    if not match:
        raise ValueError("expected host:port, e.g. 10.0.0.10:6443 or k8s.site.example:6443 ([v6]:port for IPv6)")
    host, port = match.group(1), int(match.group(2))
    if not _is_host(host):
        raise ValueError(f"'{host}' is neither an IP address nor a DNS name of lowercase letters, digits, '-' and '.'")
    if not 1 <= port <= 65535:
        raise ValueError(f"port {port} is out of range; expected 1 to 65535")
    return host, port


def _join_endpoint(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _network(value, variable: str, problems: list[Problem]):
    try:
        return ipaddress.ip_network(str(value), strict=True)
    except ValueError as exc:
        problems.append(_problem(variable, value, f"{exc}; expected a network in CIDR notation such as 10.244.0.0/16"))
        return None


def check_site(kubernetes_version, pod_cidr, service_cidr, problems: list[Problem]) -> None:
    """The version and the two networks; every problem is appended."""
    if not isinstance(kubernetes_version, str) or not _VERSION.match(kubernetes_version):
        problems.append(_problem("kuberos_kubernetes_version", kubernetes_version, "expected a version such as v1.34.4"))
    pods = _network(pod_cidr, "kuberos_pod_cidr", problems)
    services = _network(service_cidr, "kuberos_service_cidr", problems)
    if pods is not None:
        node_mask = 24 if pods.version == 4 else 64  # kube-controller-manager's default --node-cidr-mask-size
        if pods.prefixlen > node_mask:
            problems.append(
                _problem("kuberos_pod_cidr", pod_cidr, f"a /{pods.prefixlen} is smaller than one node's /{node_mask} of pods")
            )
        elif node_mask - pods.prefixlen > 16:
            problems.append(
                _problem(
                    "kuberos_pod_cidr",
                    pod_cidr,
                    f"holds more than 2^16 node subnets of /{node_mask}; use /{node_mask - 16} or longer",
                )
            )
    if services is not None and services.max_prefixlen - services.prefixlen > 20:
        problems.append(
            _problem(
                "kuberos_service_cidr",
                service_cidr,
                f"too large for Kubernetes; use /{services.max_prefixlen - 20} or a longer prefix",
            )
        )
    if pods is not None and services is not None and pods.version == services.version and pods.overlaps(services):
        problems.append(_problem("kuberos_pod_cidr", pod_cidr, f"overlaps kuberos_service_cidr {service_cidr}"))


def cluster_settings(
    control_planes: list[Machine],
    kubernetes_version=DEFAULT_KUBERNETES_VERSION,
    pod_cidr=DEFAULT_POD_CIDR,
    service_cidr=DEFAULT_SERVICE_CIDR,
    control_plane_endpoint="",
    cluster_name="kubernetes",
    cri_socket=DEFAULT_CRI_SOCKET,
    bind_port=DEFAULT_API_PORT,
    control_plane_schedulable=True,
    cgroup_driver="systemd",
    image_repository="",
    etcd_image_tag="",
    coredns_image_tag="",
    conntrack_max_per_core=None,
    eviction_hard=None,
) -> ClusterSettings:
    """Validated site settings; the endpoint defaults to the first control plane's address and port 6443."""
    problems: list[Problem] = []
    if not control_planes:
        problems.append(
            Problem(SOURCE, "groups.control_plane", "is empty; expected at least one edge host to run the control plane")
        )
    check_site(kubernetes_version, pod_cidr, service_cidr, problems)
    if not control_plane_endpoint and control_planes:
        control_plane_endpoint = _join_endpoint(control_planes[0].address, DEFAULT_API_PORT)
    endpoint_host = None
    try:
        endpoint_host, _port = split_endpoint(control_plane_endpoint)
    except ValueError as exc:
        problems.append(_problem("kuberos_control_plane_endpoint", control_plane_endpoint, str(exc)))
    if isinstance(bind_port, bool) or not isinstance(bind_port, int) or not 1 <= bind_port <= 65535:
        problems.append(_problem("bind_port", bind_port, "expected a port number from 1 to 65535"))
    if not isinstance(cri_socket, str) or not cri_socket.startswith(("unix:///", "/")):
        problems.append(_problem("cri_socket", cri_socket, "expected a socket such as unix:///run/containerd/containerd.sock"))
    if not isinstance(cluster_name, str) or not _DNS_NAME.match(cluster_name):
        problems.append(_problem("cluster_name", cluster_name, "expected a name of lowercase letters, digits and '-'"))
    if cgroup_driver not in CGROUP_DRIVERS:
        problems.append(_problem("kuberos_cgroup_driver", cgroup_driver, "expected systemd (what systemd hosts use) or cgroupfs"))
    if image_repository and (not isinstance(image_repository, str) or not _IMAGE_REPOSITORY.match(image_repository)):
        problems.append(
            _problem(
                "kuberos_kubeadm_image_repository",
                image_repository,
                "expected a registry path such as mirror.site.example:5000/k8s",
            )
        )
    if conntrack_max_per_core is not None and (
        isinstance(conntrack_max_per_core, bool) or not isinstance(conntrack_max_per_core, int) or conntrack_max_per_core < 0
    ):
        problems.append(
            _problem(
                "kuberos_kube_proxy_conntrack_max_per_core",
                conntrack_max_per_core,
                "expected a whole number of connections per CPU, or 0 to leave the host's limit alone",
            )
        )
    problems += _eviction_problems(eviction_hard)
    for variable, tag in (("kuberos_etcd_image_tag", etcd_image_tag), ("kuberos_coredns_image_tag", coredns_image_tag)):
        if tag and (not isinstance(tag, str) or not _IMAGE_TAG.match(tag)):
            problems.append(_problem(variable, tag, "expected an image tag such as 3.5.35-0 or v1.12.1"))
    if problems:
        raise SpecError(problems, "invalid kubeadm settings")
    sans: list[str] = []
    for name in [endpoint_host] + [a for m in control_planes for a in (m.address, m.vpn_address)]:
        if name and name not in sans:
            sans.append(name)
    return ClusterSettings(
        kubernetes_version=kubernetes_version,
        pod_cidr=str(pod_cidr),
        service_cidr=str(service_cidr),
        control_plane_endpoint=control_plane_endpoint,
        cert_sans=tuple(sans),
        cluster_name=cluster_name,
        cri_socket=cri_socket,
        bind_port=bind_port,
        control_plane_schedulable=bool(control_plane_schedulable),
        cgroup_driver=cgroup_driver,
        image_repository=image_repository or "",
        etcd_image_tag=etcd_image_tag or "",
        coredns_image_tag=coredns_image_tag or "",
        conntrack_max_per_core=conntrack_max_per_core,
        eviction_hard=tuple(sorted((str(k), str(v)) for k, v in (eviction_hard or {}).items())),
    )


def _eviction_problems(eviction_hard) -> list[Problem]:
    """What is wrong with kuberos_kubelet_eviction_hard: a mapping of eviction signal to threshold, or empty."""
    if eviction_hard in (None, {}):
        return []
    if not isinstance(eviction_hard, dict):
        return [_problem("kuberos_kubelet_eviction_hard", eviction_hard, "expected a mapping of eviction signal to threshold")]
    problems = []
    for signal, threshold in eviction_hard.items():
        path = f"kuberos_kubelet_eviction_hard.{signal}"
        if signal not in EVICTION_SIGNALS:
            problems.append(_problem(path, threshold, f"unknown signal; expected one of {', '.join(EVICTION_SIGNALS)}"))
        elif not isinstance(threshold, str) or not _EVICTION_THRESHOLD.match(threshold):
            problems.append(_problem(path, threshold, "expected a quantity such as 500Mi or a share such as 5%"))
    return problems


def kubelet_labels(wanted: dict[str, str]) -> tuple[dict[str, str], dict[str, str]]:
    """Split labels into those a kubelet may set on its own Node and the others (label -> reason).

    Kubernetes refuses self-set labels under kubernetes.io and k8s.io (and their subdomains), except a few
    well-known ones and the kubelet.kubernetes.io and node.kubernetes.io namespaces. ``node-role.kubernetes.io/*``
    is the classic case. Those are for the API (the ``node_labels`` role), never for ``--node-labels``.
    """
    allowed, refused = {}, {}
    for key, value in sorted(wanted.items()):
        namespace = key.split("/", 1)[0] if "/" in key else ""
        restricted = any(namespace == n or namespace.endswith("." + n) for n in _RESTRICTED_NAMESPACES)
        kubelet_namespace = any(namespace == n or namespace.endswith("." + n) for n in _KUBELET_LABEL_NAMESPACES)
        if restricted and key not in _KUBELET_LABELS and not kubelet_namespace:
            refused[key] = (
                f"a kubelet may not set labels under {namespace} on its own Node (NodeRestriction); apply it through the API"
            )
        else:
            allowed[key] = value
    return allowed, refused


def _check_labels(host: str, variable: str, wanted, problems: list[Problem]) -> dict[str, str]:
    if not isinstance(wanted, dict):
        problems.append(_problem(f"hosts.{host}.{variable}", wanted, "expected a mapping of label keys to values"))
        return {}
    good = {}
    for key, value in wanted.items():
        key, value = str(key), "" if value is None else str(value)
        prefix, _sep, name = key.rpartition("/")
        if (prefix and (len(prefix) > 253 or not _DNS_NAME.match(prefix))) or not _LABEL_NAME.match(name):
            problems.append(
                _problem(
                    f"hosts.{host}.{variable}", key, "expected a label key such as example.com/name (name up to 63 characters)"
                )
            )
        elif len(value) > 63 or not _LABEL_VALUE.match(value):
            problems.append(
                _problem(
                    f"hosts.{host}.{variable}.{key}", value, "expected a label value of up to 63 letters, digits, '-', '_', '.'"
                )
            )
        else:
            good[key] = value
    return good


# ---------------------------------------------------------------------------------------------- documents


def _args(**values) -> list[dict[str, str]]:
    """kubeadm v1beta4 extra arguments: a list of name/value pairs, skipping empty values."""
    return [{"name": name.replace("_", "-"), "value": value} for name, value in values.items() if value]


def node_ip(machine: Machine) -> str | None:
    """The address the kubelet registers: the VPN address for cloud VMs, else the site address when it is an IP."""
    if machine.node.tier == "cloud" and machine.vpn_address:
        return machine.vpn_address
    return machine.address if is_ip(machine.address) else None


def node_registration(machine: Machine, settings: ClusterSettings, control_plane: bool, self_labels: dict[str, str]) -> dict:
    """nodeRegistration: the node name, its labels through the kubelet, its taints."""
    taints = labels.node_taints(machine.node)
    registration: dict = {"name": machine.node.name, "criSocket": settings.cri_socket}
    if control_plane and not settings.control_plane_schedulable:
        taints = [{"key": "node-role.kubernetes.io/control-plane", "effect": "NoSchedule"}, *taints]
    # An empty list, not an absent key: for a control plane, absent means kubeadm's NoSchedule control-plane taint.
    registration["taints"] = taints
    node_labels = ",".join(f"{k}={v}" for k, v in sorted(self_labels.items()))
    registration["kubeletExtraArgs"] = _args(node_ip=node_ip(machine), node_labels=node_labels)
    return registration


def kubelet_configuration(cgroup_driver: str = "systemd", eviction_hard: tuple[tuple[str, str], ...] = ()) -> dict:
    """The kubelet settings kubeadm uploads for every node (kubelet-config ConfigMap); the cgroup driver must be
    containerd's (node_prereqs_cgroup_driver). ``eviction_hard`` replaces the kubelet's thresholds as a whole (a signal
    left out is not watched), so a site that sets it names every signal it wants."""
    document = {"apiVersion": KUBELET_API_VERSION, "kind": "KubeletConfiguration", "cgroupDriver": cgroup_driver}
    if eviction_hard:
        document["evictionHard"] = dict(eviction_hard)
    return document


def init_documents(machine: Machine, settings: ClusterSettings, self_labels: dict[str, str]) -> list[dict]:
    """InitConfiguration, ClusterConfiguration and KubeletConfiguration of the first control plane."""
    init = {
        "apiVersion": API_VERSION,
        "kind": "InitConfiguration",
        # kubeadm init always makes one bootstrap token (24 h unless told); the joins use tokens of their own, deleted
        # once spent, so this one is never used: it expires soon.
        "bootstrapTokens": [{"ttl": INIT_TOKEN_TTL, "description": INIT_TOKEN_DESCRIPTION}],
        "localAPIEndpoint": {"advertiseAddress": machine.address, "bindPort": settings.bind_port},
        "nodeRegistration": node_registration(machine, settings, True, self_labels),
    }
    cluster = {
        "apiVersion": API_VERSION,
        "kind": "ClusterConfiguration",
        "clusterName": settings.cluster_name,
        "kubernetesVersion": settings.kubernetes_version,
        "controlPlaneEndpoint": settings.control_plane_endpoint,
        "networking": {"podSubnet": settings.pod_cidr, "serviceSubnet": settings.service_cidr},
        "apiServer": {"certSANs": list(settings.cert_sans)},
        "etcd": {"local": {"dataDir": "/var/lib/etcd"}},  # stacked: one etcd member beside each API server
    }
    if settings.image_repository:
        cluster["imageRepository"] = settings.image_repository
    if settings.etcd_image_tag:
        cluster["etcd"]["local"]["imageTag"] = settings.etcd_image_tag
    if settings.coredns_image_tag:
        cluster["dns"] = {"imageTag": settings.coredns_image_tag}
    documents = [init, cluster, kubelet_configuration(settings.cgroup_driver, settings.eviction_hard)]
    if settings.conntrack_max_per_core is not None:
        # kube-proxy raises the host-wide nf_conntrack_max at start; a node whose network namespace cannot write it
        # (nested in a container) needs 0: leave the host's limit as it is.
        documents.append(
            {
                "apiVersion": KUBE_PROXY_API_VERSION,
                "kind": "KubeProxyConfiguration",
                "conntrack": {"maxPerCore": settings.conntrack_max_per_core},
            }
        )
    return documents


def join_documents(
    machine: Machine, settings: ClusterSettings, control_plane: bool, self_labels: dict[str, str], secrets: JoinSecrets
) -> list[dict]:
    """The JoinConfiguration of a worker, or of an additional control plane (with its local API endpoint)."""
    join: dict = {
        "apiVersion": API_VERSION,
        "kind": "JoinConfiguration",
        "discovery": {
            "bootstrapToken": {
                "apiServerEndpoint": settings.control_plane_endpoint,
                "token": secrets.token,
                "caCertHashes": list(secrets.ca_cert_hashes),
            },
        },
        "nodeRegistration": node_registration(machine, settings, control_plane, self_labels),
    }
    if control_plane:
        join["controlPlane"] = {
            "localAPIEndpoint": {"advertiseAddress": machine.address, "bindPort": settings.bind_port},
            "certificateKey": secrets.certificate_key,
        }
    return [join]


def to_yaml(documents: list[dict]) -> str:
    """A multi-document YAML file, keys in the order given."""
    return "".join("---\n" + yaml.safe_dump(doc, sort_keys=False, default_flow_style=False, width=1000) for doc in documents)


# ---------------------------------------------------------------------------------------------- secrets


def join_secrets(join_command: str | None = None, certificate_key: str | None = None) -> JoinSecrets:
    """The token and CA hash from ``kubeadm token create --print-join-command``, and the certificate key (or the
    output of ``kubeadm init phase upload-certs --upload-certs``, which ends with it). None: placeholders.

    Error messages never repeat the text they were given: it holds secrets.
    """
    if join_command is None and certificate_key is None:
        return JoinSecrets()
    token, hashes, key = PLACEHOLDER_TOKEN, (PLACEHOLDER_CA_CERT_HASH,), PLACEHOLDER_CERTIFICATE_KEY
    problems = []
    if join_command is not None:
        tokens = _TOKEN.findall(str(join_command))
        hashes = tuple(dict.fromkeys(_CA_HASH.findall(str(join_command))))
        if len(tokens) != 1 or not hashes:
            problems.append(
                Problem(
                    "kubeadm token create --print-join-command",
                    "",
                    f"found {len(tokens)} bootstrap token(s) and {len(hashes)} CA certificate hash(es); expected one "
                    "--token <6.16 lowercase letters and digits> and at least one --discovery-token-ca-cert-hash sha256:<hex>",
                )
            )
        else:
            token = tokens[0]
    if certificate_key is not None:
        keys = _CERT_KEY.findall(str(certificate_key))
        if not keys:
            problems.append(
                Problem(
                    "kubeadm init phase upload-certs --upload-certs",
                    "",
                    "no certificate key found; expected a line of 64 hexadecimal digits",
                )
            )
        else:
            key = keys[-1]
    if problems:
        raise SpecError(problems, "cannot read the join secrets")
    return JoinSecrets(token, hashes, key, placeholders=False)


# ---------------------------------------------------------------------------------------------- one host


def machine_of(inventory: Inventory, host: str, node_name: str, address, vpn_address, problems: list[Problem]) -> Machine | None:
    """The machine of one host, its addresses checked."""
    node = inventory.nodes.get(node_name)
    if node is None:
        problems.append(Problem(SOURCE, f"hosts.{host}", "is not a host of the groups robots, edge or cloud"))
        return None
    address = "" if address is None else str(address)
    if not address or not _is_host(address):
        problems.append(_problem(f"hosts.{host}.kuberos_address", address, "expected an IP address or a DNS name"))
    if vpn_address not in (None, ""):
        if not is_ip(vpn_address):
            problems.append(
                _problem(f"hosts.{host}.kuberos_vpn_address", vpn_address, "expected the host's IP address inside the tunnel")
            )
        vpn_address = str(vpn_address)
    else:
        vpn_address = None
    return Machine(host, node, address, vpn_address)


def kubeadm_config(
    inventory: Inventory,
    host: str,
    node_names: dict[str, str],
    addresses: dict[str, dict],
    control_plane_hosts: list[str],
    settings: dict | None = None,
    extra_labels: dict | None = None,
    join_command: str | None = None,
    certificate_key: str | None = None,
    init_host: str | None = None,
) -> dict:
    """What kubeadm needs on ``host``: the action (init, join-control-plane, join-worker), the documents and
    their YAML, the labels the kubelet sets and those left to the API, the taints, the API endpoint.

    ``init_host`` is the control plane that runs ``kubeadm init`` (None: the first of ``control_plane_hosts``; '': none,
    the cluster exists and every control plane joins it, the first one too when it was rebuilt).

    ``node_names`` maps inventory hosts to node names, ``addresses`` maps hosts to ``{address, vpn_address}``;
    ``settings`` holds the keyword arguments of ``cluster_settings``.
    """
    problems: list[Problem] = []
    if host not in node_names:
        raise SpecError(
            [Problem(SOURCE, f"hosts.{host}", "is not a host of the groups robots, edge or cloud")], "invalid kubeadm settings"
        )
    control_planes = []
    for index, name in enumerate(control_plane_hosts):
        if name not in node_names or inventory.nodes[node_names[name]].tier != "edge":
            problems.append(
                Problem(
                    SOURCE,
                    f"groups.control_plane[{index}]",
                    f"'{name}' is not a host of the edge group; control planes run on edge servers",
                )
            )
            continue
        given = addresses.get(name, {})
        found = machine_of(inventory, name, node_names[name], given.get("address"), given.get("vpn_address"), problems)
        if found is not None:
            control_planes.append(found)
            if not is_ip(found.address):
                problems.append(
                    _problem(
                        f"hosts.{name}.kuberos_address",
                        found.address,
                        "a control plane advertises its API server on an IP address",
                    )
                )
    own = addresses.get(host, {})
    machine = machine_of(inventory, host, node_names[host], own.get("address"), own.get("vpn_address"), problems)
    if machine is not None and machine.node.tier == "cloud" and machine.vpn_address is None:
        problems.append(
            Problem(
                SOURCE,
                f"hosts.{host}.kuberos_vpn_address",
                "is required for a cloud host; expected its IP address inside the WireGuard tunnel",
            )
        )
    wanted = dict(labels.node_labels(machine.node)) if machine else {}
    wanted.update(_check_labels(host, "kubeadm extra node labels", extra_labels or {}, problems))
    if problems:
        raise SpecError(problems, "invalid kubeadm settings")
    site = cluster_settings(control_planes, **(settings or {}))
    self_labels, refused = kubelet_labels(wanted)
    if host == (control_plane_hosts[0] if init_host is None else init_host):
        action, documents, secrets = INIT, init_documents(machine, site, self_labels), JoinSecrets()
    else:
        secrets = join_secrets(join_command, certificate_key)
        action = JOIN_CONTROL_PLANE if host in control_plane_hosts else JOIN_WORKER
        documents = join_documents(machine, site, action == JOIN_CONTROL_PLANE, self_labels, secrets)
    return {
        "action": action,
        "host": host,
        "node_name": machine.node.name,
        "control_plane_endpoint": site.control_plane_endpoint,
        "cert_sans": list(site.cert_sans),
        "labels": self_labels,
        "labels_for_api": refused,
        "taints": documents[0]["nodeRegistration"]["taints"],
        "placeholders": action != INIT and secrets.placeholders,
        "documents": documents,
        "content": to_yaml(documents),
    }
