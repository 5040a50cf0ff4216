"""Host variables as the filters read them: builtin types only, and a host's address."""

from __future__ import annotations


def plain(value):
    """Builtin types only (Ansible hands over tagged subclasses of str, int, dict..., which YAML cannot represent)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, bool) or value is None:
        return value
    for kind in (int, float, str):
        if isinstance(value, kind):
            return kind(value)
    return str(value)


def host_address(variables, host: str) -> str:
    """How the site reaches a host: its ``kuberos_address``, else ``ansible_host``, else its inventory name."""
    for key in ("kuberos_address", "ansible_host"):
        if variables.get(key) not in (None, ""):
            return str(variables[key])
    return str(host)


def node_name(variables, host: str) -> str:
    """A host's Kubernetes node name: its ``kuberos_node_name``, else its inventory name (as kubeadm_config names it)."""
    return str(variables.get("kuberos_node_name") or host)
