"""What the Kubernetes Pod Security Standards allow each rendered pod, and the settings that make it pass.

Every pod the collection renders (modules, discovery servers, bridges, batch runs, prestage pods, the controller)
passes ``restricted``: it runs as a non-root user, with no privilege escalation, every capability dropped and the
container runtime's seccomp profile. A module that asks for more says so in its spec: ``user: 0`` (root) makes its
pods ``baseline``, ``privileged: true`` makes them ``privileged``. ``level`` reads a pod spec the way the API
server's Pod Security admission does (the checks of https://kubernetes.io/docs/concepts/security/pod-security-standards/
that a pod spec can fail), so deploy knows which level each fleet namespace can enforce and says why a pod needs a
looser one; the cluster tests check that the API server agrees on every rendered pod.

Pure: plain data in, plain data out.
"""

from __future__ import annotations

LEVELS = ("restricted", "baseline", "privileged")  # strictest first
ENFORCE = "pod-security.kubernetes.io/enforce"
ENFORCE_VERSION = "pod-security.kubernetes.io/enforce-version"
WARN = "pod-security.kubernetes.io/warn"
AUDIT = "pod-security.kubernetes.io/audit"

# The user the collection's pods run as unless their module names another: the first user of the published ROS
# images (``ubuntu`` in those of Ubuntu 24.04) and of the project's own images (``ros``).
DEFAULT_USER = 1000
RUNTIME_DEFAULT_SECCOMP = {"type": "RuntimeDefault"}
# Where ROS keeps its logs when the user may have no home to write in (a user the image does not know has ``/``).
ROS_HOME = "/tmp/.ros"

# baseline: capabilities a container may add; restricted: only this one, after dropping ALL.
BASELINE_CAPABILITIES = frozenset(
    {"AUDIT_WRITE", "CHOWN", "DAC_OVERRIDE", "FOWNER", "FSETID", "KILL", "MKNOD", "NET_BIND_SERVICE", "SETFCAP", "SETGID",
     "SETPCAP", "SETUID", "SYS_CHROOT"}
)  # fmt: skip
RESTRICTED_CAPABILITIES = frozenset({"NET_BIND_SERVICE"})
RESTRICTED_VOLUMES = frozenset(
    {"configMap", "csi", "downwardAPI", "emptyDir", "ephemeral", "persistentVolumeClaim", "projected", "secret"}
)
SAFE_SYSCTLS = frozenset(
    {"kernel.shm_rmid_forced", "net.ipv4.ip_local_port_range", "net.ipv4.ip_unprivileged_port_start",
     "net.ipv4.tcp_syncookies", "net.ipv4.ping_group_range", "net.ipv4.ip_local_reserved_ports",
     "net.ipv4.tcp_keepalive_time", "net.ipv4.tcp_fin_timeout", "net.ipv4.tcp_keepalive_intvl",
     "net.ipv4.tcp_keepalive_probes"}
)  # fmt: skip
_VOLUME_KEYS = ("name",)


def container_security_context(user: int = DEFAULT_USER, privileged: bool = False) -> dict:
    """A container's securityContext: ``restricted`` for a non-root ``user``; root (``user`` 0) keeps the runtime's
    default capabilities (``baseline``); ``privileged`` is what it says. The user is set on each container (not only
    on the pod), so a batch run's pod keeps every module's own."""
    if privileged:
        return {"privileged": True, "runAsUser": user}
    if user == 0:
        return {"runAsUser": 0, "allowPrivilegeEscalation": False}
    return {
        "runAsNonRoot": True,
        "runAsUser": user,
        "runAsGroup": user,
        "allowPrivilegeEscalation": False,
        "capabilities": {"drop": ["ALL"]},
    }


def pod_security_context() -> dict:
    """The pod's securityContext: the container runtime's seccomp profile (every level allows it)."""
    return {"seccompProfile": dict(RUNTIME_DEFAULT_SECCOMP)}


def harden(pod_spec: dict, user: int = DEFAULT_USER) -> dict:
    """``pod_spec`` with the restricted settings on the pod and every container that has none of its own."""
    pod_spec["securityContext"] = {**pod_security_context(), **(pod_spec.get("securityContext") or {})}
    for container in [*pod_spec.get("initContainers", []), *pod_spec.get("containers", [])]:
        container.setdefault("securityContext", container_security_context(user))
    return pod_spec


def _containers(spec: dict) -> list[dict]:
    return [*(spec.get("initContainers") or []), *(spec.get("containers") or []), *(spec.get("ephemeralContainers") or [])]


def _baseline_problems(spec: dict) -> list[str]:
    """Why a pod spec fails ``baseline`` (empty: it passes)."""
    problems = [f"{key}: true" for key in ("hostNetwork", "hostPID", "hostIPC") if spec.get(key)]
    pod_context = spec.get("securityContext") or {}
    problems += [f"volume {v.get('name')}: hostPath" for v in spec.get("volumes") or [] if "hostPath" in v]
    problems += [f"sysctl {s.get('name')}" for s in pod_context.get("sysctls") or [] if s.get("name") not in SAFE_SYSCTLS]
    if (pod_context.get("seccompProfile") or {}).get("type") == "Unconfined":
        problems.append("seccompProfile: Unconfined")
    for container in _containers(spec):
        name, context = container.get("name"), container.get("securityContext") or {}
        if context.get("privileged"):
            problems.append(f"container {name}: privileged")
        added = set((context.get("capabilities") or {}).get("add") or ()) - BASELINE_CAPABILITIES
        if added:
            problems.append(f"container {name}: adds capabilities {', '.join(sorted(added))}")
        if any(p.get("hostPort") for p in container.get("ports") or []):
            problems.append(f"container {name}: hostPort")
        if (context.get("seccompProfile") or {}).get("type") == "Unconfined":
            problems.append(f"container {name}: seccompProfile Unconfined")
        if context.get("procMount") not in (None, "Default"):
            problems.append(f"container {name}: procMount {context['procMount']}")
    return problems


def _restricted_problems(spec: dict) -> list[str]:
    """Why a pod spec that passes ``baseline`` fails ``restricted`` (empty: it passes)."""
    pod_context = spec.get("securityContext") or {}
    problems = [
        f"volume {v.get('name')}: {kind}"
        for v in spec.get("volumes") or []
        for kind in v
        if kind not in _VOLUME_KEYS and kind not in RESTRICTED_VOLUMES
    ]
    if pod_context.get("runAsUser") == 0:
        problems.append("runAsUser: 0")
    for container in _containers(spec):
        name, context = container.get("name"), container.get("securityContext") or {}
        if context.get("allowPrivilegeEscalation") is not False:
            problems.append(f"container {name}: allowPrivilegeEscalation not false")
        if not context.get("runAsNonRoot", pod_context.get("runAsNonRoot")):
            problems.append(f"container {name}: runAsNonRoot not true")
        if context.get("runAsUser", pod_context.get("runAsUser")) == 0:
            problems.append(f"container {name}: runAsUser 0")
        seccomp = (context.get("seccompProfile") or pod_context.get("seccompProfile") or {}).get("type")
        if seccomp not in ("RuntimeDefault", "Localhost"):
            problems.append(f"container {name}: no seccompProfile RuntimeDefault")
        capabilities = context.get("capabilities") or {}
        if "ALL" not in (capabilities.get("drop") or ()):
            problems.append(f"container {name}: capabilities not dropped (drop: [ALL])")
        added = set(capabilities.get("add") or ()) - RESTRICTED_CAPABILITIES
        if added:
            problems.append(f"container {name}: adds capabilities {', '.join(sorted(added))}")
    return problems


def level(spec: dict) -> tuple[str, list[str]]:
    """The strictest Pod Security level that admits a pod spec, and why it is not the stricter one (empty for
    ``restricted``)."""
    baseline = _baseline_problems(spec)
    if baseline:
        return "privileged", baseline
    restricted = _restricted_problems(spec)
    return ("baseline", restricted) if restricted else ("restricted", [])


def loosest(levels) -> str:
    """The level a namespace can enforce for pods of these levels: the loosest of them (``restricted`` if none)."""
    return max(levels, key=LEVELS.index, default="restricted")


def namespace_labels(enforced: str) -> dict[str, str]:
    """The labels that make the API server enforce ``enforced`` in a namespace, and warn (and audit) about anything
    that would not pass ``restricted``."""
    if enforced not in LEVELS:
        raise ValueError(f"unknown Pod Security level {enforced!r}")
    return {ENFORCE: enforced, ENFORCE_VERSION: "latest", WARN: "restricted", AUDIT: "restricted"}


def pod_spec_of(obj: dict) -> dict | None:
    """The pod spec of a Pod, or of a workload's pod template (Deployment, Job, DaemonSet, StatefulSet), else None."""
    spec = obj.get("spec") or {}
    if obj.get("kind") == "Pod":
        return spec
    if obj.get("kind") == "CronJob":
        spec = (spec.get("jobTemplate") or {}).get("spec") or {}
    template = spec.get("template")
    return (template or {}).get("spec") if isinstance(template, dict) else None
