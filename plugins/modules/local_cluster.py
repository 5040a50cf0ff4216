#!/usr/bin/python
# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Start or stop the local control plane."""

from __future__ import annotations

DOCUMENTATION = r"""
module: local_cluster
short_description: Run a real Kubernetes control plane on this machine, with kwok for simulated nodes and real nodes beside them
version_added: 0.1.0
description:
  - Starts etcd, kube-apiserver, kube-controller-manager, kube-scheduler and kwok as background processes
    (pid files and logs under O(state_dir)), after generating a CA, serving and client certificates and a
    kubeconfig. TLS only, certificate authentication, anonymous access off.
  - Starting a running cluster changes nothing; a component that died is started again.
  - With O(real_nodes), runs a real node for each of them as well, a kubelet, containerd and kube-proxy in
    a network namespace per node, pod networks routed between them through a delay fabric that applies the
    inventory's round-trip times, CoreDNS for Service names, and the images of O(images) imported into every
    node (docs/real-nodes.md). Stopping removes every process, mount, cgroup, network namespace, link and
    route they made and restores the host sysctls the kubelet changes.
  - The binaries come from the role C(kuberos.platform.local_cluster), which builds them from the Go module proxy.
options:
  state:
    description: C(started) runs every component; C(stopped) stops them; C(absent) stops them and removes O(state_dir).
    type: str
    choices: [started, stopped, absent]
    default: started
  state_dir:
    description: Directory of certificates, etcd data, logs, pid files and the kubeconfig.
    type: path
    required: true
  binaries:
    description:
      - Path of each program, keys C(etcd), C(kube-apiserver), C(kube-controller-manager), C(kube-scheduler), C(kwok),
        and for real nodes C(kubelet), C(kube-proxy) and C(coredns).
    type: dict
    required: true
  real_nodes:
    description:
      - The real nodes, as returned by P(kuberos.platform.real_nodes#filter) (C(nodes) with name, labels and taints,
        C(delay_ms), and C(link_bps) and C(link_loss) for the links the inventory limits). Empty for none.
        Stopping stops the real nodes the state directory records, whatever this says.
    type: dict
    default: {}
  real_nodes_base:
    description: Second octet of the real nodes' addresses (10.B.0.0/24 control, 10.B+1.0.0/24 nodes, 10.B+2.0.0/16 pods).
    type: int
    default: 231
  real_nodes_tag:
    description: Prefix of the real nodes' network namespaces, links and cgroups (1 to 4 letters or digits).
    type: str
    default: kr
  registry_port:
    description:
      - With real nodes, run the lab's container registry (the CNCF distribution registry, Debian's C(docker-registry))
        on this port of the management bridge, with TLS and htpasswd authentication; every image of O(images) is
        pushed to it by digest and every node's containerd trusts its CA. C(0) runs none.
      - Its user is C(kuberos); the password is in C(<state_dir>/nodes/registry/password) (mode 0600), the CA
        certificate in C(<state_dir>/nodes/registry/ca.crt).
    type: int
    default: 0
  images:
    description: Image reference to OCI archive, imported into every real node's containerd (and pushed to the registry).
    type: dict
    default: {}
  image_aliases:
    description: Further names of the imported images (alias to reference), such as the names specs use.
    type: dict
    default: {}
  kwok_stages:
    description: kwok stage configuration files (node and pod lifecycle).
    type: list
    elements: path
    default: []
  ports:
    description: Ports to use, keys C(apiserver), C(etcd_client), C(etcd_peer), C(controller_manager), C(scheduler), C(kwok).
    type: dict
    default: {}
  timeout:
    description: Seconds to wait for etcd and the API server to become ready.
    type: int
    default: 90
  unreachable_toleration_s:
    description:
      - Seconds a pod without tolerations of its own stays on a node that is unreachable or not ready before it is
        evicted (the API server's C(--default-unreachable-toleration-seconds) and C(--default-not-ready-toleration-seconds);
        Kubernetes' default 300). The collection's onboard pods tolerate both for ever whatever this is.
      - Read when the API server starts; a running one keeps what it was started with.
    type: int
    default: 300
attributes:
  check_mode:
    support: full
  diff_mode:
    support: none
extends_documentation_fragment:
  - kuberos.platform.attributes
author:
  - KubeROS contributors (@kuberos)
"""

EXAMPLES = r"""
- name: Start the local control plane
  kuberos.platform.local_cluster:
    state_dir: ~/.cache/kuberos/cluster
    binaries: "{{ local_cluster__binaries }}"
"""

RETURN = r"""
kubeconfig:
  description: Path of the administrator kubeconfig.
  returned: always
  type: str
server:
  description: URL of the API server.
  returned: always
  type: str
registry:
  description:
    - The lab registry, when real nodes run with O(registry_port); C(address), C(username), C(ca_file), and C(images)
      (each built image reference to the reference that pulls it from the registry by digest). The password is not
      returned.
  returned: when real nodes run with a registry
  type: dict
components:
  description: Pid of each running component (null when not running), real nodes' as C(<node>/<component>).
  returned: always
  type: dict
actions:
  description: What was done, in order.
  returned: always
  type: list
  elements: str
"""

import os
import shutil

from ansible.module_utils.basic import AnsibleModule

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.local_control_plane import LocalControlPlane, Ports
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import (
    RealNodeError,
    RealNodes,
    host_address,
)


def main():
    module = AnsibleModule(
        argument_spec=dict(
            state=dict(type="str", choices=["started", "stopped", "absent"], default="started"),
            state_dir=dict(type="path", required=True),
            binaries=dict(type="dict", required=True),
            kwok_stages=dict(type="list", elements="path", default=[]),
            ports=dict(type="dict", default={}),
            timeout=dict(type="int", default=90),
            unreachable_toleration_s=dict(type="int", default=300),
            real_nodes=dict(type="dict", default={}),
            real_nodes_base=dict(type="int", default=231),
            real_nodes_tag=dict(type="str", default="kr"),
            images=dict(type="dict", default={}),
            image_aliases=dict(type="dict", default={}),
            registry_port=dict(type="int", default=0),
        ),
        supports_check_mode=True,
    )
    params = module.params
    try:
        ports = Ports(**{k: int(v) for k, v in params["ports"].items()})
    except TypeError as exc:
        module.fail_json(msg=f"ports: {exc}")
    # Pods on real nodes reach the API server through the `kubernetes` Service: its endpoint is the nodes' relay.
    advertise = host_address(params["real_nodes_base"]) if params["real_nodes"].get("nodes") else "127.0.0.1"
    plane = LocalControlPlane(
        params["state_dir"], params["binaries"], ports, params["kwok_stages"], advertise_address=advertise,
        unreachable_toleration_s=params["unreachable_toleration_s"],
    )  # fmt: skip
    running = plane.running()
    result = {"kubeconfig": plane.kubeconfig, "server": plane.server, "actions": []}
    real = None
    try:
        if params["state"] == "started" and params["real_nodes"].get("nodes"):
            real = RealNodes(
                plane, params["real_nodes"]["nodes"], params["real_nodes"].get("delay_ms", {}), params["binaries"],
                images=params["images"], aliases=params["image_aliases"], base=params["real_nodes_base"],
                tag=params["real_nodes_tag"], registry_port=params["registry_port"],
                links={key: params["real_nodes"].get(key, {}) for key in ("link_bps", "link_loss")},
            )  # fmt: skip
        elif params["state"] != "started":
            real = RealNodes.from_state(plane, params["binaries"])
        if real is not None:
            running.update(real.running())
        if params["state"] == "started":
            needed = [c for c, pid in running.items() if pid is None]
            if module.check_mode:
                result.update(changed=bool(needed), actions=[f"would start {c}" for c in needed])
            else:
                result["changed"] = plane.start(params["timeout"])
                if real is not None:
                    result["changed"] = real.start(params["timeout"]) or result["changed"]
        else:
            active = [c for c, pid in running.items() if pid is not None]
            gone = params["state"] == "absent" and os.path.exists(params["state_dir"])
            if module.check_mode:
                result.update(changed=bool(active) or gone, actions=[f"would stop {c}" for c in active])
            else:
                result["changed"] = real.stop(remove=params["state"] == "absent") if real is not None else False
                result["changed"] = plane.stop() or result["changed"]
                if gone:
                    shutil.rmtree(params["state_dir"])
                    plane.log.append(f"removed {params['state_dir']}")
                    result["changed"] = True
    except (RuntimeError, OSError, RealNodeError) as exc:
        log = plane.log + (real.log if real is not None else [])
        module.fail_json(msg=str(exc), actions=log, **{k: v for k, v in result.items() if k != "actions"})
    result["actions"] = result["actions"] or plane.log + (real.log if real is not None else [])
    result["components"] = {**plane.running(), **(real.running() if real is not None else {})}
    if real is not None and real.registry is not None and params["state"] == "started" and not module.check_mode:
        result["registry"] = real.registry_info()
    module.exit_json(**result)


if __name__ == "__main__":
    main()
