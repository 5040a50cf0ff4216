"""The dashboard's last lines of a module instance: its newest pod's containers, read through the controller's
access layer (pods/log in the fleets' namespaces, nothing cluster-wide).

The controller may not read Secrets, so it cannot take their values out of a log: the log of a pod whose containers
can read a Secret is not shown here (``playbooks/logs.yml``, with the deployer's rights, shows it redacted). Every
log shown has keys, passwords and tokens taken out by their shapes (``kuberos.module_logs.redact``), including the
body lines of a key whose BEGIN line is above the tail (docs/logs.md).
"""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import labels
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.module_logs import (
    labelled,
    newest_pod,
    redact,
    secret_refs,
)

DASHBOARD_LINES = 40
MAX_LINES = 200


def instance_log(kube, namespace: str, instance: str, lines: int = DASHBOARD_LINES) -> dict:
    """``{pod, node, containers, lines}`` of the instance's newest running pod, or ``{refused}`` / ``{missing}``."""
    lines = max(1, min(int(lines), MAX_LINES))
    pod = newest_pod(kube.list("Pod", namespace, selector=f"{labels.INSTANCE}={instance}"))
    if pod is None:
        return {"instance": instance, "missing": f"{instance} has no pod"}
    meta = pod["metadata"]
    secrets = sorted({name for name, _key in secret_refs(pod["spec"])})
    if secrets:
        return {"instance": instance, "pod": meta["name"],
                "refused": f"{meta['name']} can read Secret {', '.join(secrets)}: its log is shown by playbooks/logs.yml, "
                           "which keeps their values out"}  # fmt: skip
    names = [c["name"] for c in pod["spec"].get("containers") or ()]
    out: list[str] = []
    for name in names:
        text = kube.log(meta["name"], namespace, container=name, tail_lines=lines)
        out += labelled(name, redact(text, {}), len(names) > 1)
    return {"instance": instance, "pod": meta["name"], "node": pod["spec"].get("nodeName", ""), "containers": names, "lines": out}
