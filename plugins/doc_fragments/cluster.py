# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Options shared by the modules that read or change a cluster."""

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options:
  kubeconfig:
    description:
      - Path of the kubeconfig of the cluster. The local cluster's is C(<cache>/cluster/kubeconfig)
        (C(KUBEROS_CACHE_DIR), else C(~/.cache/kuberos)).
    type: path
    required: true
requirements:
  - kubernetes (Python client)
"""
